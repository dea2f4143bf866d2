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

GC_TW_ATTR static void GC_TW_NAME(walk)(const gc_grid *g, const gc_node *nd, const gc_ray *r, double ta,
                             double tb, gc_hit *hit, gc_mail *mail
#if GC_TW_COUNT
                             ,
                             gc_counts *cnt
#endif
)
{
    /* Per axis: the entry cell, the t of the next cell boundary, the t between
     * boundaries, the cells left before the walk leaves the grid (the entry
     * cell included), and the step in the flat cell index.  An axis the ray
     * does not move along has t_next = inf, dt = 0 and is never chosen. */
    int32_t c[3], left[3];
    int64_t stride[3];
    double t_next[3], dt[3];
    const int64_t axis_stride[3] = {1, (int64_t)nd->n[0], (int64_t)nd->n[0] * (int64_t)nd->n[1]};
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
    /* The walk picks the next axis without a branch: which axis a ray crosses
     * next is a coin toss for the branch predictor, and a mispredicted step
     * would cost more than the step itself.  With SSE2 the three boundary t's
     * stay in vector registers and a step adds each axis's increment under a
     * mask (x if tx <= ty and tx <= tz, else y if ty <= tz, else z: ties go to
     * the earlier axis); the integer side (the index step, the cells left
     * before the grid ends) takes the same masks.  The chain one step hands
     * to the next is then a compare, two logic operations and an add; an
     * index into per-axis arrays in memory (the other build) runs each step
     * through a store and a reload and a table lookup.  The ray and the best
     * hit are local copies, so the compiler keeps them in registers instead
     * of reloading them after every store of a hit. */
    const gc_ray ray = *r;
    double best_t = hit->t;
    int32_t best_prim = hit->prim;
#if GC_MASKED_DDA
    __m128d vtx = _mm_set_sd(t_next[0]), vty = _mm_set_sd(t_next[1]), vtz = _mm_set_sd(t_next[2]);
    const __m128d vdx = _mm_set_sd(dt[0]), vdy = _mm_set_sd(dt[1]), vdz = _mm_set_sd(dt[2]);
    const __m128d ones = _mm_castsi128_pd(_mm_set1_epi32(-1));
    int64_t lx = left[0], ly = left[1], lz = left[2];
#else
    double tn[3] = {t_next[0], t_next[1], t_next[2]};
#endif
    int64_t idx = (int64_t)gc_cell_index(nd, c[0], c[1], c[2]);
    const int64_t first = (int64_t)nd->first_cell;
    const int64_t end = first + axis_stride[2] * (int64_t)nd->n[2];
    const gc_cell *cells = g->cells;
    const uint64_t *occ = g->occ;
    const gc_pack *ref_tris = g->ref_tris;
#if GC_TW_SIMD == 4
    gc_ray4 rayv;
    gc_ray4_prepare(&rayv, &ray);
#elif GC_TW_SIMD == 2
    gc_ray2 rayv;
    gc_ray2_prepare(&rayv, &ray);
#endif
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
         * each axis end it), so next is the cell of the next step whenever there is one. */
        nc.count = 0;
        if (next >= first && next < end && gc_occupied(occ, next)) {
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
            GC_TW_NAME(walk)(g, &g->nodes[cell.begin], &ray, t_enter, t_exit, hit, mail, cnt);
#else
            GC_TW_NAME(walk)(g, &g->nodes[cell.begin], &ray, t_enter, t_exit, hit, mail);
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
                        if (GC_TW_ISECT(&ray, &pk->c[0][lane], best_t, &t)) {
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
                    int m = gc_isect_watertight_signs_avx2(&rayv, &pk->c[0][0]) & keep;
#else
                    int m = gc_isect_watertight_signs_sse2(&rayv, &pk->c[0][0]) & keep;
#endif
                    /* only the lanes that passed, lowest first */
                    while (m) {
                        const int lane = gc_lowest_bit(m);
                        m &= m - 1;
                        double t;
                        if (gc_isect_watertight_finish_inline(&ray, &pk->c[0][lane], best_t, &t)) {
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
                    if (GC_TW_ISECT(&ray, &pk->c[0][lane], best_t, &t)) {
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

/* First hit of one prepared ray. */
GC_TW_ATTR static void GC_TW_NAME(trace)(const gc_grid *g, const gc_ray *r, gc_hit *hit, gc_mail *mail
#if GC_TW_COUNT
                              ,
                              gc_counts *cnt
#endif
)
{
    const gc_node *top = &g->nodes[0];
    double t0 = 0.0, t1 = INFINITY;
    hit->t = INFINITY;
    hit->prim = -1;
    if (mail) {
        gc_mail_next_ray(mail);
    }
    if (!gc_ray_box_clip(r, top->lo, top->hi, &t0, &t1)) {
        return;
    }
#if GC_TW_COUNT
    GC_TW_NAME(walk)(g, top, r, t0, t1, hit, mail, cnt);
#else
    GC_TW_NAME(walk)(g, top, r, t0, t1, hit, mail);
#endif
}
