/* traverse_impl.h - the one source of first-hit grid traversal.
 *
 * Included by traverse.c once per (twin, intersector) with:
 *   GC_TW_COUNT  0 for the timed twin (counts compile away), 1 for the instrumented twin;
 *   GC_TW_ISECT  the ray/triangle test, gc_isect_moller_trumbore or gc_isect_watertight;
 *   GC_TW_NAME(x) the suffixing macro that names this instance's functions;
 *   GC_TW_SIMD   how the watertight test's sign stage runs over a pack of
 *                GC_LANES triangles: 0 one triangle at a time (any intersector),
 *                2 two lanes at a time (SSE2), 4 four at once (AVX2);
 *   GC_TW_ATTR   attributes of this instance's functions (the AVX2 instance is
 *                compiled for AVX2 whatever the build's flags), or nothing.
 *
 * 3D-DDA after Amanatides and Woo, "A Fast Voxel Traversal Algorithm for Ray
 * Tracing", Eurographics 1987.  A node is walked over the ray interval [ta, tb]
 * it was entered with; the entry cell is found from the entry point and clamped
 * into the grid, so an interval that rounding puts a hair outside still walks
 * the cells it covers.  A cell holding a subgrid walks the subgrid over the
 * part of the interval inside the cell.  The walk ends once the best hit so far
 * lies no farther than the current cell's exit: every triangle the ray meets
 * before that point is stored in a cell already visited.
 */

/* A ray as each of its walks reads it: the prepared ray and, for the packed sign stage,
 * its broadcast form (gc_ray4 or gc_ray2), made once a ray by the trace below, not once a
 * node entered; a nested grid's ray enters several. */
typedef struct {
    gc_ray ray;
#if GC_TW_SIMD == 4
    gc_ray4 v;
#elif GC_TW_SIMD == 2
    gc_ray2 v;
#endif
} GC_TW_NAME(wray);

GC_TW_ATTR static void GC_TW_NAME(walk)(const gc_grid *g, const gc_node *nd, const GC_TW_NAME(wray) *restrict w,
                             double ta, double tb, gc_hit *hit, gc_mail *mail
#if GC_TW_COUNT
                             ,
                             gc_counts *cnt
#endif
)
{
    /* The walk reads the ray where the trace made it (restrict: no store of the walk's
     * reaches it), rather than a copy of its own each node. */
    const gc_ray *restrict r = &w->ray;
    /* Per axis: the entry cell, the t of the next cell boundary, the t between
     * boundaries, the cells left before the walk leaves the grid (the entry
     * cell included), and the step in the flat cell index.  An axis the ray
     * does not move along has t_next = inf, dt = 0 and is never chosen. */
    int32_t c[3];
    int64_t stride[3];
    const int64_t axis_stride[3] = {1, (int64_t)nd->n[0], (int64_t)nd->n[0] * (int64_t)nd->n[1]};
#if GC_TW_SIMD == 4 && GC_MASKED_DDA
    /* The same operations as the loop below (the other builds'), on the three axes
     * at once: lane i of each vector is axis i's value, lane 3 is not used.  Every
     * lane's arithmetic is the scalar code's (IEEE operations in the same order, no
     * contraction; floor is roundpd toward -inf, the clamp maxpd then minpd, and the
     * integers are exact in double), so the walk is the same walk. */
    __m128d vtx, vty, vtz, vdx, vdy, vdz;
    int64_t lx, ly, lz;
    {
        const __m256d o = gc_load3_avx2(r->o), d = gc_load3_avx2(r->d), inv_d = gc_load3_avx2(r->inv_d);
        const __m256d lo = gc_load3_avx2(nd->lo), hi = gc_load3_avx2(nd->hi);
        const __m256d cell = gc_load3_avx2(nd->cell), inv_cell = gc_load3_avx2(nd->inv_cell);
        const __m256d n =
            _mm256_cvtepi32_pd(_mm_insert_epi32(_mm_loadu_si128((const __m128i *)(const void *)nd->n), 0, 3));
        const __m256d zero = _mm256_setzero_pd(), one = _mm256_set1_pd(1.0);
        const __m256d p = _mm256_add_pd(o, _mm256_mul_pd(_mm256_set1_pd(ta), d));
        const __m256d f = _mm256_round_pd(_mm256_mul_pd(_mm256_sub_pd(p, lo), inv_cell),
                                          _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
        const __m256d cf = _mm256_min_pd(_mm256_max_pd(f, zero), _mm256_sub_pd(n, one));
        const __m256d pos = _mm256_cmp_pd(d, zero, _CMP_GT_OQ);
        const __m256d moves = _mm256_cmp_pd(d, zero, _CMP_NEQ_UQ);
        /* cells left: n - c going up, c + 1 down, c + 2 (never reached) along an axis
         * the ray does not move along */
        __m256d left = _mm256_blendv_pd(_mm256_add_pd(cf, one), _mm256_sub_pd(n, cf), pos);
        left = _mm256_blendv_pd(_mm256_add_pd(cf, _mm256_set1_pd(2.0)), left, moves);
        /* the boundary ahead, the grid's last face its box's own */
        const __m256d e = _mm256_add_pd(cf, _mm256_and_pd(pos, one));
        const __m256d edge = _mm256_blendv_pd(_mm256_add_pd(lo, _mm256_mul_pd(e, cell)), hi,
                                              _mm256_cmp_pd(e, n, _CMP_EQ_OQ));
        const __m256d t_next = _mm256_blendv_pd(_mm256_set1_pd(INFINITY),
                                                _mm256_mul_pd(_mm256_sub_pd(edge, o), inv_d), moves);
        const __m256d dt = _mm256_and_pd(gc_fabs_avx2(_mm256_mul_pd(cell, inv_d)), moves);
        const __m128i ci = _mm256_cvttpd_epi32(cf), li = _mm256_cvttpd_epi32(left);
        c[0] = _mm_cvtsi128_si32(ci);
        c[1] = _mm_extract_epi32(ci, 1);
        c[2] = _mm_extract_epi32(ci, 2);
        lx = _mm_cvtsi128_si32(li);
        ly = _mm_extract_epi32(li, 1);
        lz = _mm_extract_epi32(li, 2);
        /* the index step: +-1 times the axis's stride, 0 along an axis the ray does not move along */
        const __m256d sgn = _mm256_and_pd(_mm256_blendv_pd(_mm256_set1_pd(-1.0), one, pos), moves);
        const __m128i si = _mm256_cvttpd_epi32(sgn);
        stride[0] = _mm_cvtsi128_si32(si);
        stride[1] = (int64_t)_mm_extract_epi32(si, 1) * axis_stride[1];
        stride[2] = (int64_t)_mm_extract_epi32(si, 2) * axis_stride[2];
        const __m128d t_lo = _mm256_castpd256_pd128(t_next), t_hi = _mm256_extractf128_pd(t_next, 1);
        const __m128d d_lo = _mm256_castpd256_pd128(dt), d_hi = _mm256_extractf128_pd(dt, 1);
        vtx = t_lo;
        vty = _mm_unpackhi_pd(t_lo, t_lo);
        vtz = t_hi;
        vdx = d_lo;
        vdy = _mm_unpackhi_pd(d_lo, d_lo);
        vdz = d_hi;
    }
#else
    int32_t left[3];
    double t_next[3], dt[3];
    for (int i = 0; i < 3; ++i) {
        double p = r->o[i] + ta * r->d[i];
        double f = floor((p - nd->lo[i]) * nd->inv_cell[i]);
        double top = (double)(nd->n[i] - 1);
        c[i] = (int32_t)gc_clamp_cell(f, top); /* NaN-free: p is finite */
        /* A ray's direction signs are coin tosses for the branch predictor
         * (three a node entered): the sign enters as a number, and the one
         * branch left, on a zero component, is almost never taken. */
        if (r->d[i] != 0.0) {
            const int32_t pos = r->d[i] > 0.0;
            const int32_t n_i = (int32_t)nd->n[i];
            left[i] = c[i] + 1 + pos * (n_i - 2 * c[i] - 1); /* n - c going up, c + 1 down */
            stride[i] = (2 * (int64_t)pos - 1) * axis_stride[i];
            /* the boundary ahead: the cell's upper face going up, its lower face going down;
             * the grid's last face is its box's own */
            const int32_t e = c[i] + pos;
            const double edges[2] = {nd->lo[i] + (double)e * nd->cell[i], nd->hi[i]};
            t_next[i] = (edges[e == n_i] - r->o[i]) * r->inv_d[i];
            dt[i] = fabs(nd->cell[i] * r->inv_d[i]);
        } else {
            left[i] = c[i] + 2; /* never reached */
            stride[i] = 0;
            t_next[i] = INFINITY;
            dt[i] = 0.0;
        }
    }
#endif
    /* The walk picks the next axis without a branch: which axis a ray crosses
     * next is a coin toss for the branch predictor, and a mispredicted step
     * would cost more than the step itself.  With SSE2 the three boundary t's
     * stay in vector registers and a step adds each axis's increment under a
     * mask (x if tx <= ty and tx <= tz, else y if ty <= tz, else z: ties go to
     * the earlier axis); the integer side (the index step, the cells left
     * before the grid ends) takes the same masks.  The chain one step hands
     * to the next is then a compare, two logic operations and an add; an
     * index into per-axis arrays in memory (the other build) runs each step
     * through a store and a reload and a table lookup.  The best hit is a local
     * copy, so the compiler keeps it in registers instead of reloading it after
     * every store of a hit. */
    double best_t = hit->t;
    int32_t best_prim = hit->prim;
#if !(GC_TW_SIMD == 4 && GC_MASKED_DDA)
#if GC_MASKED_DDA
    __m128d vtx = _mm_set_sd(t_next[0]), vty = _mm_set_sd(t_next[1]), vtz = _mm_set_sd(t_next[2]);
    const __m128d vdx = _mm_set_sd(dt[0]), vdy = _mm_set_sd(dt[1]), vdz = _mm_set_sd(dt[2]);
    int64_t lx = left[0], ly = left[1], lz = left[2];
#else
    double tn[3] = {t_next[0], t_next[1], t_next[2]};
#endif
#endif
#if GC_MASKED_DDA
    const __m128d ones = _mm_castsi128_pd(_mm_set1_epi32(-1));
#endif
    int64_t idx = (int64_t)gc_cell_index(nd, c[0], c[1], c[2]);
    const gc_cell *cells = g->cells;
    const uint64_t *occ = g->occ;
    const gc_pack *ref_tris = g->ref_tris;
#if !GC_MASKED_DDA
    /* the axis whose boundary comes first, indexed by the three comparisons */
    static const uint8_t next_axis[8] = {2, 1, 2, 1, 2, 1, 0, 0};
#endif
    double t_enter = ta;
#if GC_TW_COUNT
    /* occupancy changes along this walk: the cell before the first counts as occupied */
    uint32_t prev_occupied = 1;
#endif
    /* The record of the cell the walk is in, read only where the cell's occupancy bit
     * is set: most cells a ray steps through are empty, and their bits stay cached where
     * the records of a grid of many MB would not.  The first cell's is read here, each
     * next one's a step ahead (the look-ahead below), so the branch on it waits for no
     * load. */
    gc_cell nc = {0, 0};
    if (gc_occupied(occ, idx)) {
        nc = cells[idx];
    }
    for (;;) {
#if GC_MASKED_DDA
        const __m128d mx = _mm_and_pd(_mm_cmple_sd(vtx, vty), _mm_cmple_sd(vtx, vtz));
        const __m128d my = _mm_andnot_pd(mx, _mm_cmple_sd(vty, vtz));
        const __m128d mz = _mm_andnot_pd(_mm_or_pd(mx, my), ones);
        const double t_axis = _mm_cvtsd_f64(_mm_min_sd(_mm_min_sd(vtx, vty), vtz));
        /* all ones or zero, per axis */
        const int64_t ix = _mm_cvtsi128_si64(_mm_castpd_si128(mx));
        const int64_t iy = _mm_cvtsi128_si64(_mm_castpd_si128(my));
        const int64_t iz = _mm_cvtsi128_si64(_mm_castpd_si128(mz));
        const int64_t next = idx + ((stride[0] & ix) | (stride[1] & iy) | (stride[2] & iz));
#else
        const double tx = tn[0], ty = tn[1], tz = tn[2];
        double t_axis = tx < ty ? tx : ty;
        t_axis = t_axis < tz ? t_axis : tz;
        const int a = next_axis[((tx <= ty) << 2) | ((tx <= tz) << 1) | (ty <= tz)];
        const int64_t next = idx + stride[a];
#endif
        const double t_exit = t_axis < tb ? t_axis : tb;
        const gc_cell cell = nc;
#if GC_TW_COUNT
        cnt->steps++;
        {
            const uint32_t occupied = cell.count != 0;
            cnt->changes += occupied != prev_occupied;
            prev_occupied = occupied;
        }
#endif
        /* The next cell's record, if occupied, and the first of its triangles start
         * loading while this cell is tested: a cell's triangles lie at a place in memory
         * nothing else predicts, and waiting for them made an occupied cell cost several
         * empty ones.  The walk goes on only into a cell of this node (the cells left on
         * each axis end it), so next is the cell of the next step whenever there is one;
         * where there is none, next is one step outside the node, another node's cell or
         * one of the zero bits around the array (gc_occupied), and what is read there is
         * never used. */
        nc.count = 0;
        if (gc_occupied(occ, next)) {
            nc = cells[next];
            if (nc.count != GC_CELL_SUBGRID) {
                GC_PREFETCH(ref_tris + nc.begin / GC_LANES);
            }
        }
        if (cell.count == GC_CELL_SUBGRID) {
            hit->t = best_t;
            hit->prim = best_prim;
#if GC_TW_COUNT
            cnt->subgrids++;
            GC_TW_NAME(walk)(g, &g->nodes[cell.begin], w, t_enter, t_exit, hit, mail, cnt);
#else
            GC_TW_NAME(walk)(g, &g->nodes[cell.begin], w, t_enter, t_exit, hit, mail);
#endif
            best_t = hit->t;
            best_prim = hit->prim;
        } else if (cell.count != 0) {
#if GC_TW_COUNT
            cnt->visits++;
#endif
            /* best_prim holds the mesh's face index, read from the pack beside
             * the triangle's coordinates */
            if (mail) {
                const gc_pack *pk = ref_tris + cell.begin / GC_LANES;
                uint32_t lane = cell.begin % GC_LANES;
                for (uint32_t k = 0; k < cell.count; ++k) {
                    const int32_t prim = pk->id[lane];
                    if (mail->stamp[prim] != mail->ray) {
                        mail->stamp[prim] = mail->ray;
#if GC_TW_COUNT
                        cnt->tests++;
#endif
                        double t;
                        if (GC_TW_ISECT(r, &pk->c[0][lane], best_t, &t)) {
                            best_t = t;
                            best_prim = prim;
                        }
                    }
                    const uint32_t wrap = ++lane == GC_LANES;
                    lane = wrap ? 0 : lane;
                    pk += wrap;
                }
            } else {
#if GC_TW_COUNT
                cnt->tests += cell.count;
#endif
#if GC_TW_SIMD
                /* Whole packs covering [begin, end): the sign stage of every lane
                 * at once, then the rest of the test for each lane that passed,
                 * in reference order, so each sees the best hit of those before
                 * it exactly as one at a time would.  Lanes outside the cell are
                 * masked off. */
                const int full = (1 << GC_LANES) - 1;
                const uint32_t last = cell.begin + cell.count - 1;
                const gc_pack *pk = ref_tris + cell.begin / GC_LANES;
                const gc_pack *const pk_last = ref_tris + last / GC_LANES;
                int keep = full & (full << (cell.begin % GC_LANES)); /* lanes of this cell */
                const int keep_last = full >> (GC_LANES - 1 - last % GC_LANES);
                /* One branch per pack, the loop's own: the last pack's mask is a
                 * select (how many packs a cell spans is a coin toss). */
                for (;; ++pk) {
                    const int is_last = pk == pk_last;
                    keep &= is_last ? keep_last : full;
#if GC_TW_SIMD == 4
                    int m = gc_isect_watertight_signs_avx2(&w->v, &pk->c[0][0]) & keep;
#else
                    int m = gc_isect_watertight_signs_sse2(&w->v, &pk->c[0][0]) & keep;
#endif
                    /* only the lanes that passed, lowest first */
                    while (m) {
                        const int lane = gc_lowest_bit(m);
                        m &= m - 1;
                        double t;
                        if (gc_isect_watertight_finish_inline(r, &pk->c[0][lane], best_t, &t)) {
                            best_t = t;
                            best_prim = pk->id[lane];
                        }
                    }
                    if (is_last) {
                        break;
                    }
                    keep = full;
                }
#else
                const gc_pack *pk = ref_tris + cell.begin / GC_LANES;
                uint32_t lane = cell.begin % GC_LANES;
                for (uint32_t k = 0; k < cell.count; ++k) {
                    double t;
                    if (GC_TW_ISECT(r, &pk->c[0][lane], best_t, &t)) {
                        best_t = t;
                        best_prim = pk->id[lane];
                    }
                    const uint32_t wrap = ++lane == GC_LANES;
                    lane = wrap ? 0 : lane;
                    pk += wrap;
                }
#endif
            }
        }
        if (best_t <= t_exit || !(t_exit < tb)) {
            break;
        }
        idx = next;
#if GC_MASKED_DDA
        /* adding +0 leaves the other axes' t as they were */
        vtx = _mm_add_sd(vtx, _mm_and_pd(mx, vdx));
        vty = _mm_add_sd(vty, _mm_and_pd(my, vdy));
        vtz = _mm_add_sd(vtz, _mm_and_pd(mz, vdz));
        lx += ix;
        ly += iy;
        lz += iz;
        if ((lx == 0) | (ly == 0) | (lz == 0)) {
            break;
        }
#else
        tn[a] += dt[a];
        if (--left[a] == 0) {
            break;
        }
#endif
        t_enter = t_axis;
    }
    hit->t = best_t;
    hit->prim = best_prim;
}

/* First hit of one prepared ray (w->ray); the trace fills in w->v. */
GC_TW_ATTR static void GC_TW_NAME(trace)(const gc_grid *g, GC_TW_NAME(wray) *w, gc_hit *hit, gc_mail *mail
#if GC_TW_COUNT
                              ,
                              gc_counts *cnt
#endif
)
{
    const gc_ray *r = &w->ray;
    const gc_node *top = &g->nodes[0];
    double t0 = 0.0, t1 = INFINITY;
    hit->t = INFINITY;
    hit->prim = -1;
    if (mail) {
        gc_mail_next_ray(mail);
    }
#if GC_TW_SIMD == 4 && GC_MASKED_DDA
    if (!gc_ray_box_clip_avx2(r, top->lo, top->hi, &t0, &t1)) {
        return;
    }
#else
    if (!gc_ray_box_clip(r, top->lo, top->hi, &t0, &t1)) {
        return;
    }
#endif
#if GC_TW_SIMD == 4
    gc_ray4_prepare(&w->v, r);
#elif GC_TW_SIMD == 2
    gc_ray2_prepare(&w->v, r);
#endif
#if GC_TW_COUNT
    GC_TW_NAME(walk)(g, top, w, t0, t1, hit, mail, cnt);
#else
    GC_TW_NAME(walk)(g, top, w, t0, t1, hit, mail);
#endif
}
