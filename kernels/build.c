/* build.c - uniform and nested grid construction.
 *
 * One routine builds one (sub)grid over a list of triangles: each triangle is
 * tested against the cells its bounding box spans (exact separating-axis test,
 * or bounds only), every (cell, triangle) pair is recorded, and a counting sort
 * turns the pairs into per-cell ranges of one flat reference array.  A cell
 * that will hold a subgrid passes its sorted triangle list to the same routine,
 * recursively, instead of storing references.
 *
 * Every size is checked before it is allocated: a resolution whose cell count
 * overflows the 32-bit cell offsets, a reference count that overflows them, or
 * a grid that would pass the memory limit is refused with a message.
 *
 * The triangles are read from the mesh through its faces, in the Morton order
 * of their centroids (scan_faces), and a reference is a face index: the build
 * keeps no copy of the triangles until it lays each reference's triangle in the
 * packs that traversal reads.
 *
 * With params.threads > 1 the passes over many triangles or references (the
 * face scan and its radix sort, the pair collection, the counting sort by cell
 * and the per-reference copies) run in that many contiguous parts at once, and
 * the parts are joined in order, so the grid is the same, byte for byte, as one
 * thread builds.  Built with GC_NO_THREADS, or where a thread cannot start, the
 * parts run one after the other on the calling thread.
 */
#if !defined(GC_NO_THREADS) && !defined(_POSIX_C_SOURCE)
#define _POSIX_C_SOURCE 200809L /* pthreads under -std=c99 */
#endif
#include "gc_internal.h"
#include "overlap.h"

#if defined(__SSE2__)
#include <emmintrin.h> /* cell_range */
#endif

#include <float.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#ifndef GC_NO_THREADS
#include <pthread.h>
#endif

/* Cells are widened by this fraction of their size (plus a few ulps of their
 * coordinates) when triangles are inserted, so a triangle touching a cell
 * within rounding is stored in it and traversal never misses it. */
#define GC_CELL_WIDEN_FRACTION 1e-7
#define GC_CELL_WIDEN_ULPS 8.0

/* The fewest items worth a part of their own. */
#define GC_MIN_PART_ITEMS 16384

typedef struct {
    gc_grid *g;
    int64_t cap_nodes, cap_cells, cap_refs;
    uint64_t limit;        /* memory limit, bytes */
    uint64_t scratch;      /* bytes of scratch held by the builders on the stack */
    const gc_build_params *p;
    char *err;
    int threads;           /* parts a pass may be split into (>= 1) */
    int64_t rows2_base;    /* subgrid_resolutions2: first row of the depth-1 subgrid being built */
    int64_t rows2_next;    /* ... and of the next one */
    const gc_mesh *mesh;   /* the triangles: each reference is a face index into it */
#ifndef GC_NO_THREADS
    pthread_mutex_t lock;  /* guards scratch and err while parts run */
#endif
} builder;

static void builder_lock(builder *b)
{
#ifndef GC_NO_THREADS
    if (b->threads > 1) {
        pthread_mutex_lock(&b->lock);
    }
#else
    (void)b;
#endif
}

static void builder_unlock(builder *b)
{
#ifndef GC_NO_THREADS
    if (b->threads > 1) {
        pthread_mutex_unlock(&b->lock);
    }
#else
    (void)b;
#endif
}

/* Parts for a pass over n items: one per GC_MIN_PART_ITEMS, at most b->threads. */
static int parts_for(const builder *b, int64_t n)
{
    int64_t k = n / GC_MIN_PART_ITEMS;
    return k < 1 ? 1 : (k < b->threads ? (int)k : b->threads);
}

/* First item of part k of n items in `parts` parts, rounded down to a multiple of
 * `align` (so that parts never share a pack); part `parts` starts at n. */
static int64_t part_start(int64_t n, int k, int parts, int64_t align)
{
    if (k >= parts) {
        return n;
    }
    int64_t s = (int64_t)((double)n * (double)k / (double)parts);
    return s - s % align;
}

typedef void (*part_fn)(void *job);

#ifndef GC_NO_THREADS
typedef struct {
    part_fn fn;
    void *job;
} part_call;

static void *part_thread(void *arg)
{
    part_call *c = arg;
    c->fn(c->job);
    return NULL;
}
#endif

/* fn(jobs + k * job_size) for k = 0 .. parts - 1: part 0 on the calling thread,
 * the others on threads of their own (or on the calling thread, after part 0, if
 * a thread cannot start).  Returns when every part is done. */
static void run_parts(part_fn fn, void *jobs, size_t job_size, int parts)
{
    char *base = jobs;
#ifndef GC_NO_THREADS
    pthread_t tid[GC_MAX_THREADS];
    part_call call[GC_MAX_THREADS];
    int started[GC_MAX_THREADS];
    for (int k = 1; k < parts; ++k) {
        call[k].fn = fn;
        call[k].job = base + (size_t)k * job_size;
        started[k] = pthread_create(&tid[k], NULL, part_thread, &call[k]) == 0;
    }
    fn(base);
    for (int k = 1; k < parts; ++k) {
        if (started[k]) {
            pthread_join(tid[k], NULL);
        } else {
            fn(base + (size_t)k * job_size);
        }
    }
#else
    for (int k = 0; k < parts; ++k) {
        fn(base + (size_t)k * job_size);
    }
#endif
}

typedef struct {
    uint32_t cell;
    uint32_t prim;
} pair;

static uint64_t grid_bytes(const builder *b)
{
    const gc_grid *g = b->g;
    return (uint64_t)g->n_refs * sizeof(gc_tri) +
           (uint64_t)b->cap_nodes * sizeof(gc_node) +
           (uint64_t)b->cap_cells * sizeof(gc_cell) + (uint64_t)b->cap_refs * sizeof(uint32_t);
}

static gc_status check_memory(builder *b, uint64_t extra, const char *what)
{
    uint64_t total = grid_bytes(b) + b->scratch + extra;
    if (total > b->limit) {
        gc_set_error(b->err,
                     "%s would take the grid to %.3g GiB, over the memory limit of %.3g GiB",
                     what, (double)total / (double)(1u << 30), (double)b->limit / (double)(1u << 30));
        return GC_ERR_MEMORY_LIMIT;
    }
    return GC_OK;
}

/* Grow an array to hold `need` elements (doubling), checking the memory limit. */
static gc_status reserve(builder *b, void **arr, int64_t *cap, int64_t need, size_t elem,
                         const char *what)
{
    if (need <= *cap) {
        return GC_OK;
    }
    int64_t cap2 = *cap ? *cap : 64;
    while (cap2 < need) {
        cap2 = cap2 > INT64_MAX / 2 ? need : cap2 * 2;
    }
    uint64_t extra = (uint64_t)(cap2 - *cap) * elem;
    if (grid_bytes(b) + b->scratch + extra > b->limit) {
        cap2 = need; /* try the exact size before refusing */
        extra = (uint64_t)(cap2 - *cap) * elem;
    }
    gc_status st = check_memory(b, extra, what);
    if (st != GC_OK) {
        return st;
    }
    void *p = realloc(*arr, (size_t)cap2 * elem);
    if (!p) {
        gc_set_error(b->err, "out of memory growing %s to %lld entries", what, (long long)cap2);
        return GC_ERR_NO_MEMORY;
    }
    *arr = p;
    *cap = cap2;
    return GC_OK;
}

#if !defined(__SSE2__) /* else cell_range does it in SSE2 */
/* Cell index range [*i0, *i1] that [a, b] spans along axis `ax` of node `nd`. */
static void axis_range(const gc_node *nd, int ax, double a, double b, int32_t *i0, int32_t *i1)
{
    double fa = (a - nd->lo[ax]) * nd->inv_cell[ax];
    double fb = (b - nd->lo[ax]) * nd->inv_cell[ax];
    double top = (double)(nd->n[ax] - 1);
    /* Clamped to [0, top] first, the conversion's truncation is the floor.  NaN (a cell
     * of zero width: a subgrid narrower than an ulp of its position) clamps to 0. */
    fa = !(fa > 0.0) ? 0.0 : (fa > top ? top : fa);
    fb = !(fb > 0.0) ? 0.0 : (fb > top ? top : fb);
    *i0 = (int32_t)fa;
    *i1 = (int32_t)fb;
}
#endif

/* The widened box of cell (x, y, z). */
static void cell_box(const gc_node *nd, int32_t x, int32_t y, int32_t z, double lo[3], double hi[3])
{
    int32_t c[3] = {x, y, z};
    for (int i = 0; i < 3; ++i) {
        double a = nd->lo[i] + (double)c[i] * nd->cell[i];
        double b = (c[i] + 1 == nd->n[i]) ? nd->hi[i] : nd->lo[i] + (double)(c[i] + 1) * nd->cell[i];
        double w = GC_CELL_WIDEN_FRACTION * nd->cell[i] +
                   GC_CELL_WIDEN_ULPS * DBL_EPSILON * GC_MAX(fabs(a), fabs(b));
        lo[i] = a - w;
        hi[i] = b + w;
    }
}

/* Resolution of a subgrid over `n` references in a box of extents `ext` from the
 * per-level rule: total cells M = (scale * n)^exponent, n_i = d_i cbrt(M / V),
 * computed in log space so nothing overflows. */
static void rule_resolution(const gc_build_params *p, int depth, double n, const double ext[3],
                            int32_t res[3])
{
    double log_m = p->level_exponent[depth] * log(p->level_scale[depth] * n);
    double log_v = log(ext[0]) + log(ext[1]) + log(ext[2]);
    double maxr = p->rule_max_axis > 0 ? (double)p->rule_max_axis : 1.0;
    for (int i = 0; i < 3; ++i) {
        double r = exp(log(ext[i]) + (log_m - log_v) / 3.0);
        r = floor(r + 0.5);
        if (!(r >= 1.0)) {
            r = 1.0;
        }
        if (r > maxr) {
            r = maxr;
        }
        res[i] = (int32_t)r;
    }
}

static gc_status check_resolution(builder *b, const int32_t res[3], int depth)
{
    for (int i = 0; i < 3; ++i) {
        if (res[i] < 1) {
            gc_set_error(b->err, "resolution %dx%dx%d at level %d: every axis needs at least 1 cell",
                         res[0], res[1], res[2], depth + 1);
            return GC_ERR_ARGUMENT;
        }
    }
    double cells = (double)res[0] * (double)res[1] * (double)res[2];
    if (cells > (double)GC_MAX_CELLS || (double)b->g->n_cells + cells > (double)GC_MAX_CELLS) {
        gc_set_error(b->err,
                     "resolution %dx%dx%d = %.0f cells at level %d overflows the grid's 32-bit cell "
                     "offsets (at most %llu cells in all)",
                     res[0], res[1], res[2], cells, depth + 1, (unsigned long long)GC_MAX_CELLS);
        return GC_ERR_OVERFLOW;
    }
    return GC_OK;
}

static gc_status build_node(builder *b, const uint32_t *prims, int64_t n_prims, const double lo[3],
                            const double hi[3], const int32_t res[3], int depth, uint32_t *node_out);

/* Scratch memory counted against the limit while a level is being built. */
static void *scratch_alloc(builder *b, size_t bytes, const char *what, gc_status *st)
{
    *st = check_memory(b, bytes, what);
    if (*st != GC_OK) {
        return NULL;
    }
    void *p = malloc(bytes ? bytes : 1);
    if (!p) {
        gc_set_error(b->err, "out of memory allocating %s (%zu bytes)", what, bytes);
        *st = GC_ERR_NO_MEMORY;
        return NULL;
    }
    b->scratch += bytes;
    return p;
}

static void scratch_free(builder *b, void *p, size_t bytes)
{
    free(p);
    b->scratch -= bytes;
}

/* Double the pair scratch (the rare path of collect_part; parts may call it at once). */
static gc_status grow_pairs(builder *b, pair **pairs, int64_t *cap)
{
    gc_status st = GC_OK;
    builder_lock(b);
    if ((uint64_t)*cap >= GC_MAX_REFS) {
        gc_set_error(b->err,
                     "more than %llu triangle references in one grid level: "
                     "the resolution is too fine for 32-bit reference offsets",
                     (unsigned long long)GC_MAX_REFS);
        st = GC_ERR_OVERFLOW;
        goto done;
    }
    int64_t cap2 = *cap * 2;
    size_t grow = (size_t)(cap2 - *cap) * sizeof(pair);
    st = check_memory(b, grow, "the triangle references");
    if (st != GC_OK) {
        goto done;
    }
    pair *p2 = realloc(*pairs, (size_t)cap2 * sizeof(pair));
    if (!p2) {
        gc_set_error(b->err, "out of memory recording triangle references");
        st = GC_ERR_NO_MEMORY;
        goto done;
    }
    b->scratch += grow;
    *pairs = p2;
    *cap = cap2;
done:
    builder_unlock(b);
    return st;
}

/* Faces are read in an order of their own (the Morton order of their centroids,
 * or a cell's references), so their corners are gathered from all over the mesh:
 * start loading the face PREFETCH_AHEAD items ahead, and the corners of the one
 * half as far ahead, whose face was asked for earlier. */
#define PREFETCH_AHEAD 16
GC_INLINE void prefetch_face(const double *vert, const int64_t *faces, const uint32_t *order, int64_t k,
                             int64_t end)
{
    if (k + PREFETCH_AHEAD < end) {
        GC_PREFETCH(faces + 3 * (int64_t)order[k + PREFETCH_AHEAD]);
    }
    if (k + PREFETCH_AHEAD / 2 < end) {
        const int64_t *fv = faces + 3 * (int64_t)order[k + PREFETCH_AHEAD / 2];
        GC_PREFETCH(vert + 3 * fv[0]);
        GC_PREFETCH(vert + 3 * fv[1]);
        GC_PREFETCH(vert + 3 * fv[2]);
    }
}

/* A triangle's bounds [bmin, bmax], the cells [r0, r1] its widened bounds span in
 * node nd, how many axes they spread along (span several cells or leave the node)
 * and an axis they do not (the last such, or 0): per axis as axis_range and
 * the widening in cell_box have it, operation for operation.  With SSE2 the x and
 * y axes share one register and z takes another, whose minimum, maximum,
 * comparison and conversion instructions give the scalar code's results (a
 * clamp's NaN to 0 included). */
typedef struct {
    const gc_node *nd;
    double fcell[3]; /* GC_CELL_WIDEN_FRACTION times the cell size */
    double top[3];   /* the last cell's index */
} range_consts;

static void range_consts_init(range_consts *c, const gc_node *nd)
{
    c->nd = nd;
    for (int i = 0; i < 3; ++i) {
        c->fcell[i] = GC_CELL_WIDEN_FRACTION * nd->cell[i];
        c->top[i] = (double)(nd->n[i] - 1);
    }
}

GC_INLINE void cell_range(const range_consts *c, const double *v0, const double *v1, const double *v2,
                          double bmin[3], double bmax[3], int32_t r0[3], int32_t r1[3], int *spread_out,
                          int *slab_out)
{
    const gc_node *nd = c->nd;
#if defined(__SSE2__)
    /* the slab axis for each set of spreading axes (bit i: axis i spreads) */
    static const int8_t last_clear[8] = {2, 2, 2, 2, 1, 1, 0, 0};
    const __m128d ulps = _mm_set1_pd(GC_CELL_WIDEN_ULPS * DBL_EPSILON);
    const __m128d zero = _mm_setzero_pd();
    const __m128d sign = _mm_set1_pd(-0.0);
    __m128d lo[2], hi[2];
    __m128i q0[2], q1[2];
    int mask = 0;
    for (int h = 0; h < 2; ++h) { /* h = 0: x and y; h = 1: z (its upper lane unused) */
        __m128d a0, a1, a2, nlo, nhi, inv, fcell, top;
        if (h == 0) {
            a0 = _mm_loadu_pd(v0), a1 = _mm_loadu_pd(v1), a2 = _mm_loadu_pd(v2);
            nlo = _mm_loadu_pd(nd->lo), nhi = _mm_loadu_pd(nd->hi), inv = _mm_loadu_pd(nd->inv_cell);
            fcell = _mm_loadu_pd(c->fcell), top = _mm_loadu_pd(c->top);
        } else {
            a0 = _mm_load_sd(v0 + 2), a1 = _mm_load_sd(v1 + 2), a2 = _mm_load_sd(v2 + 2);
            nlo = _mm_load_sd(nd->lo + 2), nhi = _mm_load_sd(nd->hi + 2), inv = _mm_load_sd(nd->inv_cell + 2);
            fcell = _mm_load_sd(c->fcell + 2), top = _mm_load_sd(c->top + 2);
        }
        /* GC_MIN(a, b) is _mm_min_pd(a, b), GC_MAX(a, b) _mm_max_pd(a, b) */
        const __m128d a = _mm_min_pd(a0, _mm_min_pd(a1, a2)), z = _mm_max_pd(a0, _mm_max_pd(a1, a2));
        const __m128d w =
            _mm_add_pd(fcell, _mm_mul_pd(ulps, _mm_max_pd(_mm_andnot_pd(sign, a), _mm_andnot_pd(sign, z))));
        const __m128d aw = _mm_sub_pd(a, w), zw = _mm_add_pd(z, w);
        /* !(f > 0) ? 0 : (f > top ? top : f) */
        const __m128d fa = _mm_min_pd(_mm_max_pd(_mm_mul_pd(_mm_sub_pd(aw, nlo), inv), zero), top);
        const __m128d fb = _mm_min_pd(_mm_max_pd(_mm_mul_pd(_mm_sub_pd(zw, nlo), inv), zero), top);
        lo[h] = a, hi[h] = z;
        q0[h] = _mm_cvttpd_epi32(fa);
        q1[h] = _mm_cvttpd_epi32(fb);
        /* the two int32 lanes of q0 != q1, widened to the two double lanes */
        const __m128d ne = _mm_castsi128_pd(
            _mm_shuffle_epi32(_mm_xor_si128(_mm_cmpeq_epi32(q0[h], q1[h]), _mm_set1_epi32(-1)), 0x50));
        const __m128d out = _mm_or_pd(_mm_cmplt_pd(aw, nlo), _mm_cmpgt_pd(zw, nhi));
        mask |= (_mm_movemask_pd(_mm_or_pd(ne, out)) & (h == 0 ? 3 : 1)) << (2 * h);
    }
    _mm_storeu_pd(bmin, lo[0]);
    _mm_store_sd(bmin + 2, lo[1]);
    _mm_storeu_pd(bmax, hi[0]);
    _mm_store_sd(bmax + 2, hi[1]);
    r0[0] = _mm_cvtsi128_si32(q0[0]);
    r0[1] = _mm_cvtsi128_si32(_mm_shuffle_epi32(q0[0], 1));
    r0[2] = _mm_cvtsi128_si32(q0[1]);
    r1[0] = _mm_cvtsi128_si32(q1[0]);
    r1[1] = _mm_cvtsi128_si32(_mm_shuffle_epi32(q1[0], 1));
    r1[2] = _mm_cvtsi128_si32(q1[1]);
    *spread_out = (mask & 1) + (mask >> 1 & 1) + (mask >> 2 & 1);
    *slab_out = last_clear[mask];
#else
    int spread = 0, slab = 0;
    for (int i = 0; i < 3; ++i) {
        double a = GC_MIN(v0[i], GC_MIN(v1[i], v2[i]));
        double z = GC_MAX(v0[i], GC_MAX(v1[i], v2[i]));
        bmin[i] = a;
        bmax[i] = z;
        double w = c->fcell[i] + GC_CELL_WIDEN_ULPS * DBL_EPSILON * GC_MAX(fabs(a), fabs(z));
        axis_range(nd, i, a - w, z + w, &r0[i], &r1[i]);
        const int spreads = (r0[i] != r1[i]) | (a - w < nd->lo[i]) | (z + w > nd->hi[i]);
        spread += spreads;
        slab = spreads ? slab : i;
    }
    *spread_out = spread;
    *slab_out = slab;
#endif
}

/* One part of collect_pairs: the pairs of a contiguous run of the node's triangles. */
typedef struct {
    builder *b;
    const gc_node *nd;
    const uint32_t *prims;
    int64_t n_prims;
    int exact;
    const double *clo[3], *chi[3], *cmid[3], *chalf[3]; /* the widened cells per axis */
    pair *pairs;                                        /* scratch of cap entries */
    int64_t n, cap;
    gc_status st;
} collect_job;

static void collect_part(void *arg)
{
    collect_job *j = arg;
    builder *b = j->b;
    const gc_node *nd = j->nd;
    const int exact = j->exact;
    const double *const *clo = j->clo, *const *chi = j->chi, *const *cmid = j->cmid,
                        *const *chalf = j->chalf;
    pair *pairs = j->pairs;
    int64_t n = 0, cap = j->cap;
    gc_status st = GC_OK;
    const int64_t nx = nd->n[0], nxy = (int64_t)nd->n[0] * nd->n[1];
    const double *vert = b->mesh->vertices;
    const int64_t *faces = b->mesh->faces;
    range_consts cr;
    range_consts_init(&cr, nd);
    for (int64_t k = 0; k < j->n_prims; ++k) {
        const uint32_t prim = j->prims[k];
        prefetch_face(vert, faces, j->prims, k, j->n_prims);
        const int64_t *fv = faces + 3 * (int64_t)prim;
        const double *v0 = vert + 3 * fv[0], *v1 = vert + 3 * fv[1], *v2 = vert + 3 * fv[2];
        int32_t r0[3], r1[3];
        double bmin[3], bmax[3];
        int spread, slab;
        cell_range(&cr, v0, v1, v2, bmin, bmax, r0, r1, &spread, &slab);
        const int64_t span = (int64_t)(r1[0] - r0[0] + 1) * (r1[1] - r0[1] + 1) * (r1[2] - r0[2] + 1);
        /* Bounds in one cell, or in one row of cells whose cross-section holds
         * them: the triangle lies inside the (widened) row, and being connected it
         * meets every widened cell of the row that its bounds meet, so of the
         * separating-axis test only the bounds comparison (the box axes) can
         * reject a cell of the row. */
        if (span == 1 || spread <= 1 || !exact) { /* every cell of the bounds */
            const int row = exact && span > 1;
            while (n + span > cap) {
                if ((st = grow_pairs(b, &pairs, &cap)) != GC_OK) {
                    goto out;
                }
            }
            for (int32_t z = r0[2]; z <= r1[2]; ++z) {
                for (int32_t y = r0[1]; y <= r1[1]; ++y) {
                    for (int32_t x = r0[0]; x <= r1[0]; ++x) {
                        if (row && gc_bounds_apart(bmin, bmax, clo[0][x], clo[1][y], clo[2][z], chi[0][x],
                                                   chi[1][y], chi[2][z])) {
                            continue;
                        }
                        pairs[n].cell = (uint32_t)(x + nx * y + nxy * z);
                        pairs[n].prim = prim;
                        ++n;
                    }
                }
            }
            continue;
        }
        /* bounds in one slab of cells along axis `slab` (spread 2): the test in 2D */
        const int in_slab = spread == 2;
        gc_tri_box_prep prep;
        gc_tri_slab_prep sp;
        if (in_slab) {
            gc_tri_slab_prepare(&sp, v0, v1, v2, slab);
        } else {
            gc_tri_box_prepare(&prep, v0, v1, v2);
        }
        for (int32_t z = r0[2]; z <= r1[2]; ++z) {
            const double lo2 = clo[2][z], hi2 = chi[2][z], m2 = cmid[2][z], h2 = chalf[2][z];
            for (int32_t y = r0[1]; y <= r1[1]; ++y) {
                const double lo1 = clo[1][y], hi1 = chi[1][y], m1 = cmid[1][y], h1 = chalf[1][y];
                for (int32_t x = r0[0]; x <= r1[0]; ++x) {
                    if (!(in_slab ? gc_tri_slab_prepared_overlap(&sp, clo[0][x], lo1, lo2, chi[0][x], hi1, hi2,
                                                                 cmid[0][x], m1, m2, chalf[0][x], h1, h2)
                                  : gc_tri_box_prepared_overlap(&prep, clo[0][x], lo1, lo2, chi[0][x], hi1, hi2,
                                                                cmid[0][x], m1, m2, chalf[0][x], h1, h2))) {
                        continue;
                    }
                    if (n == cap && (st = grow_pairs(b, &pairs, &cap)) != GC_OK) {
                        goto out;
                    }
                    pairs[n].cell = (uint32_t)(x + nx * y + nxy * z);
                    pairs[n].prim = prim;
                    ++n;
                }
            }
        }
    }
out:
    j->pairs = pairs;
    j->n = n;
    j->cap = cap;
    j->st = st;
}

static void free_pair_parts(builder *b, collect_job *jobs, int parts)
{
    for (int k = 0; k < parts; ++k) {
        if (jobs[k].pairs) {
            scratch_free(b, jobs[k].pairs, (size_t)jobs[k].cap * sizeof(pair));
            jobs[k].pairs = NULL;
        }
    }
}

/* Record every (cell, triangle) pair of node `nd`, in `*parts_out` parts over
 * contiguous runs of prims: jobs[k].pairs holds jobs[k].n pairs (scratch of
 * jobs[k].cap entries; release with free_pair_parts), and the parts in order are
 * the pairs in the order of prims.  The widened cell bounds, centres and half
 * sizes along each axis are tabulated once per node (cell_box). */
static gc_status collect_pairs(builder *b, const gc_node *nd, const uint32_t *prims, int64_t n_prims,
                               collect_job jobs[GC_MAX_THREADS], int *parts_out)
{
    gc_status st = GC_OK;
    const int exact = b->p->insertion == GC_INSERT_EXACT;
    const int64_t n_axis = (int64_t)nd->n[0] + nd->n[1] + nd->n[2];
    const size_t tab_bytes = exact ? (size_t)n_axis * 4 * sizeof(double) : 0;
    double *tab = exact ? scratch_alloc(b, tab_bytes, "the cell bounds", &st) : NULL;
    if (exact && !tab) {
        return st;
    }
    const int parts = parts_for(b, n_prims);
    memset(jobs, 0, (size_t)parts * sizeof *jobs);
    for (int k = 0; k < parts && st == GC_OK; ++k) {
        collect_job *j = &jobs[k];
        const int64_t s0 = part_start(n_prims, k, parts, 1), s1 = part_start(n_prims, k + 1, parts, 1);
        j->b = b;
        j->nd = nd;
        j->prims = prims + s0;
        j->n_prims = s1 - s0;
        j->exact = exact;
        j->cap = j->n_prims > 0 ? j->n_prims : 1;
        j->pairs = scratch_alloc(b, (size_t)j->cap * sizeof(pair), "the triangle references", &st);
    }
    if (st != GC_OK) {
        free_pair_parts(b, jobs, parts);
        if (tab) {
            scratch_free(b, tab, tab_bytes);
        }
        return st;
    }
    /* tab: per axis i, from base[i], the cells' widened lo, hi, centre and half size */
    if (exact) {
        int64_t base = 0;
        for (int i = 0; i < 3; ++i) {
            double *lo = tab + base, *hi = lo + n_axis, *mid = hi + n_axis, *half = mid + n_axis;
            for (int32_t c = 0; c < nd->n[i]; ++c) {
                int32_t xyz[3] = {0, 0, 0};
                double l3[3], h3[3];
                xyz[i] = c;
                cell_box(nd, xyz[0], xyz[1], xyz[2], l3, h3);
                lo[c] = l3[i];
                hi[c] = h3[i];
                mid[c] = 0.5 * (l3[i] + h3[i]);
                half[c] = 0.5 * (h3[i] - l3[i]);
            }
            for (int k = 0; k < parts; ++k) {
                jobs[k].clo[i] = lo, jobs[k].chi[i] = hi, jobs[k].cmid[i] = mid, jobs[k].chalf[i] = half;
            }
            base += nd->n[i];
        }
    }
    run_parts(collect_part, jobs, sizeof *jobs, parts);
    if (tab) {
        scratch_free(b, tab, tab_bytes);
    }
    for (int k = 0; k < parts; ++k) {
        if (jobs[k].st != GC_OK) {
            st = jobs[k].st;
            break;
        }
    }
    if (st != GC_OK) {
        free_pair_parts(b, jobs, parts);
        return st;
    }
    *parts_out = parts;
    return GC_OK;
}

/* The counting sort of a node's pairs by cell, in parts over contiguous ranges of
 * cells [c0, c1): each part reads every pair and takes those of its cells, so the
 * parts write disjoint counters and slots, and each cell's references keep the
 * order of the pairs (the order of prims), as one thread sorts them. */
typedef struct {
    const collect_job *jobs; /* the pairs, in jobs[0 .. parts - 1] */
    int parts;
    uint32_t *off;           /* ncell + 1 counters */
    uint32_t *sorted;
    gc_cell *cells;          /* a uniform grid's cells, written by the scatter; or NULL */
    uint32_t c0, c1;
} sort_job;

static void sort_count_part(void *arg)
{
    sort_job *s = arg;
    const uint32_t c0 = s->c0, span = s->c1 - s->c0;
    uint32_t *off = s->off;
    memset(off + c0 + 1, 0, (size_t)span * sizeof *off);
    for (int k = 0; k < s->parts; ++k) {
        const pair *pairs = s->jobs[k].pairs;
        for (int64_t q = 0; q < s->jobs[k].n; ++q) {
            if (pairs[q].cell - c0 < span) {
                off[pairs[q].cell + 1]++;
            }
        }
    }
}

static void sort_scatter_part(void *arg)
{
    sort_job *s = arg;
    const uint32_t c0 = s->c0, span = s->c1 - s->c0;
    uint32_t *off = s->off, *sorted = s->sorted;
    uint32_t begin = off[c0]; /* the part's first cell's first slot */
    for (int k = 0; k < s->parts; ++k) { /* the parts in order: the pairs in the order of prims */
        const pair *pairs = s->jobs[k].pairs;
        for (int64_t q = 0; q < s->jobs[k].n; ++q) {
            if (pairs[q].cell - c0 < span) {
                sorted[off[pairs[q].cell]++] = pairs[q].prim;
            }
        }
    }
    if (s->cells) { /* each offset now the end of its cell */
        for (uint32_t c = c0; c < s->c1; ++c) {
            s->cells[c].begin = begin;
            s->cells[c].count = off[c] - begin;
            begin = off[c];
        }
    }
}

/* Resolution of the subgrid for local cell `c` of node `nd` (depth `depth`), or
 * all zeros for no subgrid. */
static void subgrid_resolution(builder *b, const gc_node *nd, int depth, int64_t c, uint32_t count,
                               int32_t res[3])
{
    const gc_build_params *p = b->p;
    res[0] = res[1] = res[2] = 0;
    if (depth + 1 >= p->levels) {
        return;
    }
    if (depth == 0 && p->subgrid_resolutions) {
        const int32_t *r = p->subgrid_resolutions + 3 * c;
        if (r[0] > 0 || r[1] > 0 || r[2] > 0) {
            res[0] = r[0];
            res[1] = r[1];
            res[2] = r[2];
        }
        return;
    }
    if (depth == 1 && p->subgrid_resolutions2) {
        const int32_t *r = p->subgrid_resolutions2 + 3 * (b->rows2_base + c);
        if (r[0] > 0 || r[1] > 0 || r[2] > 0) {
            res[0] = r[0];
            res[1] = r[1];
            res[2] = r[2];
        }
        return;
    }
    if (count <= p->subdivide_threshold) {
        return;
    }
    rule_resolution(p, depth + 1, (double)count, nd->cell, res);
    if (res[0] == 1 && res[1] == 1 && res[2] == 1) {
        res[0] = res[1] = res[2] = 0; /* a 1x1x1 subgrid would only add an entry cost */
    }
}

static gc_status build_node(builder *b, const uint32_t *prims, int64_t n_prims, const double lo[3],
                            const double hi[3], const int32_t res[3], int depth, uint32_t *node_out)
{
    gc_status st = check_resolution(b, res, depth);
    if (st != GC_OK) {
        return st;
    }
    gc_grid *g = b->g;
    const int64_t ncell = (int64_t)res[0] * res[1] * res[2];

    /* the node and its cells */
    st = reserve(b, (void **)&g->nodes, &b->cap_nodes, g->n_nodes + 1, sizeof(gc_node), "the subgrids");
    if (st != GC_OK) {
        return st;
    }
    if (!g->cells && b->p->levels == 1) {
        /* a uniform grid's cells, its only node's: their final array, mapped as
         * gc_big_move would map them (no doubling slack, no copy at the end) */
        st = check_memory(b, (uint64_t)ncell * sizeof(gc_cell), "the cells");
        if (st != GC_OK) {
            return st;
        }
        g->cells = gc_big_alloc_raw((size_t)ncell * sizeof(gc_cell), &g->cells_mapped, 0); /* every cell written below */
        if (!g->cells) {
            gc_set_error(b->err, "out of memory allocating %lld cells", (long long)ncell);
            return GC_ERR_NO_MEMORY;
        }
        b->cap_cells = ncell;
    } else {
        st = reserve(b, (void **)&g->cells, &b->cap_cells, g->n_cells + ncell, sizeof(gc_cell), "the cells");
        if (st != GC_OK) {
            return st;
        }
    }
    const uint32_t node_index = (uint32_t)g->n_nodes++;
    const uint32_t first = (uint32_t)g->n_cells;
    g->n_cells += ncell;
    gc_node nd;
    memset(&nd, 0, sizeof nd);
    for (int i = 0; i < 3; ++i) {
        nd.lo[i] = lo[i];
        nd.hi[i] = hi[i];
        nd.n[i] = res[i];
        nd.cell[i] = (hi[i] - lo[i]) / (double)res[i];
        nd.inv_cell[i] = (double)res[i] / (hi[i] - lo[i]);
    }
    nd.first_cell = first;
    nd.depth = (uint32_t)depth;
    g->nodes[node_index] = nd;
    if (depth + 1 > g->levels) {
        g->levels = depth + 1;
    }

    /* pairs, then a counting sort by cell */
    collect_job jobs[GC_MAX_THREADS];
    int parts = 0;
    int64_t n_pairs = 0;
    st = collect_pairs(b, &nd, prims, n_prims, jobs, &parts);
    if (st != GC_OK) {
        return st;
    }
    for (int k = 0; k < parts; ++k) {
        n_pairs += jobs[k].n;
    }
    if ((uint64_t)n_pairs > GC_MAX_REFS) { /* each part stayed under it, their sum did not */
        gc_set_error(b->err,
                     "more than %llu triangle references in one grid level: "
                     "the resolution is too fine for 32-bit reference offsets",
                     (unsigned long long)GC_MAX_REFS);
        free_pair_parts(b, jobs, parts);
        return GC_ERR_OVERFLOW;
    }
    size_t off_bytes = (size_t)(ncell + 1) * sizeof(uint32_t);
    size_t sorted_bytes = (size_t)(n_pairs > 0 ? n_pairs : 1) * sizeof(uint32_t);
    uint32_t *off = scratch_alloc(b, off_bytes, "the cell offsets", &st);
    uint32_t *sorted = off ? scratch_alloc(b, sorted_bytes, "the sorted references", &st) : NULL;
    if (!sorted) {
        if (off) {
            scratch_free(b, off, off_bytes);
        }
        free_pair_parts(b, jobs, parts);
        return st;
    }
    /* the top level of a uniform grid: the sorted references are the grid's */
    const int uniform_top = depth + 1 >= b->p->levels && !g->refs;
    {
        sort_job sj[GC_MAX_THREADS];
        const int sparts = parts_for(b, ncell < n_pairs ? ncell : n_pairs);
        for (int t = 0; t < sparts; ++t) {
            sj[t].jobs = jobs;
            sj[t].parts = parts;
            sj[t].off = off;
            sj[t].sorted = sorted;
            sj[t].cells = uniform_top ? g->cells + first : NULL;
            sj[t].c0 = (uint32_t)part_start(ncell, t, sparts, 1);
            sj[t].c1 = (uint32_t)part_start(ncell, t + 1, sparts, 1);
        }
        off[0] = 0;
        run_parts(sort_count_part, sj, sizeof *sj, sparts);
        for (int64_t c = 0; c < ncell; ++c) {
            off[c + 1] += off[c];
        }
        run_parts(sort_scatter_part, sj, sizeof *sj, sparts);
        for (int64_t c = ncell; c > 0 && !uniform_top; --c) { /* the scatter advanced each offset to its end */
            off[c] = off[c - 1];
        }
        off[0] = 0;
    }
    free_pair_parts(b, jobs, parts);

    if (uniform_top) { /* the scatter wrote the cells */
        g->refs = sorted;
        b->scratch -= sorted_bytes;
        b->cap_refs = (int64_t)(sorted_bytes / sizeof(uint32_t));
        g->n_refs = n_pairs;
        scratch_free(b, off, off_bytes);
        *node_out = node_index;
        return GC_OK;
    }
    /* leaf cells take their references; crowded cells get a subgrid */
    for (int64_t c = 0; c < ncell && st == GC_OK; ++c) {
        uint32_t count = off[c + 1] - off[c];
        int32_t sub[3];
        subgrid_resolution(b, &nd, depth, c, count, sub);
        if (sub[0] > 0) {
            int32_t x = (int32_t)(c % res[0]), y = (int32_t)((c / res[0]) % res[1]),
                    z = (int32_t)(c / ((int64_t)res[0] * res[1]));
            double clo[3], chi[3];
            int32_t cc[3] = {x, y, z};
            for (int i = 0; i < 3; ++i) {
                clo[i] = nd.lo[i] + (double)cc[i] * nd.cell[i];
                chi[i] = (cc[i] + 1 == nd.n[i]) ? nd.hi[i] : nd.lo[i] + (double)(cc[i] + 1) * nd.cell[i];
            }
            if (depth == 0) { /* the rows of subgrid_resolutions2 this subgrid's cells take */
                b->rows2_base = b->rows2_next;
                b->rows2_next += (int64_t)sub[0] * sub[1] * sub[2];
            }
            uint32_t child;
            st = build_node(b, sorted + off[c], (int64_t)count, clo, chi, sub, depth + 1, &child);
            if (st == GC_OK) {
                g->cells[first + c].begin = child;
                g->cells[first + c].count = GC_CELL_SUBGRID;
            }
        } else {
            if ((uint64_t)g->n_refs + count > GC_MAX_REFS) {
                gc_set_error(b->err, "more than %llu triangle references in the grid: the resolution "
                                     "is too fine for 32-bit reference offsets",
                             (unsigned long long)GC_MAX_REFS);
                st = GC_ERR_OVERFLOW;
                break;
            }
            if (g->n_refs + count > b->cap_refs) {
                st = reserve(b, (void **)&g->refs, &b->cap_refs, g->n_refs + count, sizeof(uint32_t),
                             "the triangle references");
                if (st != GC_OK) {
                    break;
                }
            }
            if (count > 0) {
                memcpy(g->refs + g->n_refs, sorted + off[c], (size_t)count * sizeof(uint32_t));
            }
            g->cells[first + c].begin = (uint32_t)g->n_refs;
            g->cells[first + c].count = count;
            g->n_refs += count;
        }
    }
    scratch_free(b, sorted, sorted_bytes);
    scratch_free(b, off, off_bytes);
    *node_out = node_index;
    return st;
}

/* Spread the low 10 bits of x to every third bit (Morton encoding). */
static uint32_t spread_bits(uint32_t x)
{
    x &= 0x3ffu;
    x = (x | x << 16) & 0x030000ffu;
    x = (x | x << 8) & 0x0300f00fu;
    x = (x | x << 4) & 0x030c30c3u;
    x = (x | x << 2) & 0x09249249u;
    return x;
}

/* One part of scan_faces: faces [f0, f1) checked, bounded and coded. */
typedef struct {
    const gc_mesh *mesh;
    int64_t f0, f1;
    double klo[3], scale[3], top;
    uint64_t *codes;     /* the faces' Morton codes, or NULL: the mesh's order ... */
    uint32_t *order;     /* ... written here */
    double lo[3], hi[3]; /* out: bounds of the part's vertices */
    int bad;             /* out: an index out of range or a vertex not finite */
} scan_job;

static void scan_part(void *arg)
{
    scan_job *j = arg;
    const double *v = j->mesh->vertices;
    const int64_t *fv = j->mesh->faces;
    const uint64_t nv = (uint64_t)j->mesh->n_vertices;
    const double top = j->top;
    double l0 = INFINITY, l1 = INFINITY, l2 = INFINITY;
    double h0 = -INFINITY, h1 = -INFINITY, h2 = -INFINITY;
    int bad = 0;
    for (int64_t f = j->f0; f < j->f1; ++f) {
        if (f + PREFETCH_AHEAD / 2 < j->f1) { /* the corners a few faces ahead (in range: not checked yet) */
            for (int c = 0; c < 3; ++c) {
                const uint64_t ic = (uint64_t)fv[3 * (f + PREFETCH_AHEAD / 2) + c];
                if (ic < nv) {
                    GC_PREFETCH(v + 3 * ic);
                }
            }
        }
        const int64_t i0 = fv[3 * f], i1 = fv[3 * f + 1], i2 = fv[3 * f + 2];
        if (((uint64_t)i0 >= nv) | ((uint64_t)i1 >= nv) | ((uint64_t)i2 >= nv)) {
            bad = 1;
            break;
        }
        const double *p0 = v + 3 * i0, *p1 = v + 3 * i1, *p2 = v + 3 * i2;
        /* x - x is 0 for a finite x and NaN for an infinite or NaN one */
        if (!((p0[0] - p0[0]) + (p0[1] - p0[1]) + (p0[2] - p0[2]) + (p1[0] - p1[0]) + (p1[1] - p1[1]) +
                  (p1[2] - p1[2]) + (p2[0] - p2[0]) + (p2[1] - p2[1]) + (p2[2] - p2[2]) ==
              0.0)) {
            bad = 1;
            break;
        }
        l0 = GC_MIN(l0, GC_MIN(p0[0], GC_MIN(p1[0], p2[0])));
        l1 = GC_MIN(l1, GC_MIN(p0[1], GC_MIN(p1[1], p2[1])));
        l2 = GC_MIN(l2, GC_MIN(p0[2], GC_MIN(p1[2], p2[2])));
        h0 = GC_MAX(h0, GC_MAX(p0[0], GC_MAX(p1[0], p2[0])));
        h1 = GC_MAX(h1, GC_MAX(p0[1], GC_MAX(p1[1], p2[1])));
        h2 = GC_MAX(h2, GC_MAX(p0[2], GC_MAX(p1[2], p2[2])));
        if (!j->codes) {
            j->order[f] = (uint32_t)f;
            continue;
        }
        uint32_t q[3];
        for (int i = 0; i < 3; ++i) {
            double u = ((p0[i] + p1[i] + p2[i]) * (1.0 / 3.0) - j->klo[i]) * j->scale[i];
            u = u > 0.0 ? (u < top ? u : top) : 0.0; /* NaN (an overflow times 0) clamps to 0 */
            q[i] = (uint32_t)u;
        }
        uint64_t code = spread_bits(q[0]) | spread_bits(q[1]) << 1 | spread_bits(q[2]) << 2;
        j->codes[f] = code << 32 | (uint64_t)(uint32_t)f;
    }
    j->lo[0] = l0, j->lo[1] = l1, j->lo[2] = l2;
    j->hi[0] = h0, j->hi[1] = h1, j->hi[2] = h2;
    j->bad = bad;
}

/* One part of a pass of the radix sort in scan_faces: items [k0, k1) of src. */
enum { RADIX_BITS = 10, RADIX_BUCKETS = 1 << RADIX_BITS };
typedef struct {
    const uint64_t *src;
    uint64_t *dst;       /* the pass's output, or NULL for the last pass ... */
    uint32_t *order;     /* ... which writes the face indices here instead */
    int64_t k0, k1;
    int shift;
    uint32_t *count;     /* RADIX_BUCKETS counters: the part's digit counts, then its first slots */
} radix_job;

static void radix_count_part(void *arg)
{
    radix_job *j = arg;
    memset(j->count, 0, RADIX_BUCKETS * sizeof *j->count);
    for (int64_t k = j->k0; k < j->k1; ++k) {
        j->count[(j->src[k] >> j->shift) & (RADIX_BUCKETS - 1)]++;
    }
}

static void radix_scatter_part(void *arg)
{
    radix_job *j = arg;
    uint32_t *slot = j->count;
    if (j->dst) {
        for (int64_t k = j->k0; k < j->k1; ++k) {
            const uint64_t x = j->src[k];
            j->dst[slot[(x >> j->shift) & (RADIX_BUCKETS - 1)]++] = x;
        }
    } else {
        for (int64_t k = j->k0; k < j->k1; ++k) {
            const uint64_t x = j->src[k];
            j->order[slot[(x >> j->shift) & (RADIX_BUCKETS - 1)]++] = (uint32_t)x;
        }
    }
}

/* The size of a mesh (its faces' and vertices' bytes) from which the Morton order
 * pays for its sort when the mesh's order is scattered: on a 2-core AMD EPYC,
 * sorting a shuffled sphere's faces cost 4-7% at 250k faces (9 MB), was even at
 * 500k (18 MB) and saved 5-10% at 10^6 (36 MB) and 13% at 5x10^6; below the caches'
 * reach the order of the reads matters less than the sort's passes. */
#define SORT_MIN_BYTES ((uint64_t)16 << 20)

/* Whether the mesh's own face order is scattered in space.  Of (at most)
 * SAMPLE_PAIRS pairs of consecutive faces, evenly spread over the mesh, a pair
 * is near when the centroids lie no farther apart on any axis than the sum of
 * the two faces' largest extents (always so for faces that touch).  A mesh most
 * of whose sampled pairs are near (scans, CAD exports, strips: faces written
 * as their surface is walked) keeps its order, which is then as local as the
 * Morton order; any other (a soup, shuffled faces) is put in Morton order.  A
 * sampled face with an index out of range or a corner that is not finite is
 * not near (the face pass then refuses the mesh). */
enum { SAMPLE_PAIRS = 1024 };
static int faces_scattered(const gc_mesh *mesh)
{
    const int64_t n = mesh->n_faces;
    const uint64_t nv = (uint64_t)mesh->n_vertices;
    const int64_t pairs = n - 1 < SAMPLE_PAIRS ? n - 1 : SAMPLE_PAIRS;
    int64_t near = 0;
    for (int64_t s = 0; s < pairs; ++s) {
        const int64_t f = s * (n - 1) / pairs; /* < n - 1 */
        const int64_t *fv = mesh->faces + 3 * f;
        int ok = 1;
        for (int c = 0; c < 6; ++c) {
            ok &= (uint64_t)fv[c] < nv;
        }
        if (!ok) {
            continue;
        }
        double mid[2][3], ext[2] = {0.0, 0.0};
        for (int t = 0; t < 2; ++t) {
            const double *p0 = mesh->vertices + 3 * fv[3 * t], *p1 = mesh->vertices + 3 * fv[3 * t + 1],
                         *p2 = mesh->vertices + 3 * fv[3 * t + 2];
            for (int i = 0; i < 3; ++i) {
                const double lo = GC_MIN(p0[i], GC_MIN(p1[i], p2[i])), hi = GC_MAX(p0[i], GC_MAX(p1[i], p2[i]));
                mid[t][i] = 0.5 * (lo + hi);
                ext[t] = GC_MAX(ext[t], hi - lo);
            }
        }
        const double reach = ext[0] + ext[1];
        near += (fabs(mid[0][0] - mid[1][0]) <= reach) & (fabs(mid[0][1] - mid[1][1]) <= reach) &
                (fabs(mid[0][2] - mid[1][2]) <= reach);
    }
    return 2 * near < pairs;
}

/* One pass over the faces that validates the mesh as gc_check_mesh does, takes
 * the bounds [vlo, vhi] of the vertices the faces use, and puts the faces in
 * Morton order of their centroids where the mesh is large (SORT_MIN_BYTES) and its
 * own order scattered (faces_scattered), in the mesh's order elsewhere (order
 * receives the n face indices).
 *
 * The codes take 10 bits per axis of the box of every finite vertex, which a
 * sequential pass over the vertices finds before the faces are read, so that the
 * faces' vertices are gathered once.  The order only keeps triangles that are
 * near in space near in memory (1024 cells a side is finer than the grid levels
 * it serves); a stray unused vertex coarsens it and changes nothing else.  The
 * sort is an LSD radix sort of (code << 32 | face) words, stable, so equal codes
 * keep the mesh's order, its passes split in parts like the scan (radix_job).
 * On a bad mesh gc_check_mesh names the first fault. */
static gc_status scan_faces(builder *b, const gc_mesh *mesh, double vlo[3], double vhi[3], uint32_t *order)
{
    enum { AXIS_BITS = 10, PASSES = 3 }; /* 30 code bits, RADIX_BITS a pass */
    const int64_t n = mesh->n_faces, nv = mesh->n_vertices;
    size_t bytes = (size_t)(n > 0 ? n : 1) * sizeof(uint64_t);
    const int parts = parts_for(b, n);
    const size_t count_bytes = (size_t)parts * RADIX_BUCKETS * sizeof(uint32_t);
    const int sort = (uint64_t)(n + nv) * 24 >= SORT_MIN_BYTES && faces_scattered(mesh);
    gc_status st = GC_OK;
    uint64_t *a = NULL, *tmp = NULL;
    uint32_t *counts = NULL;
    if (sort) {
        a = scratch_alloc(b, bytes, "the triangle order", &st);
        tmp = a ? scratch_alloc(b, bytes, "the triangle order", &st) : NULL;
        counts = tmp ? scratch_alloc(b, count_bytes, "the triangle order", &st) : NULL;
        if (!counts) {
            if (tmp) {
                scratch_free(b, tmp, bytes);
            }
            if (a) {
                scratch_free(b, a, bytes);
            }
            return st;
        }
    }
    const double *v = mesh->vertices;
    double klo[3] = {INFINITY, INFINITY, INFINITY}, khi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (int64_t k = 0; sort && k < nv; ++k) {
        const double *p = v + 3 * k;
        if ((p[0] - p[0]) + (p[1] - p[1]) + (p[2] - p[2]) == 0.0) { /* finite */
            for (int i = 0; i < 3; ++i) {
                klo[i] = GC_MIN(klo[i], p[i]);
                khi[i] = GC_MAX(khi[i], p[i]);
            }
        }
    }
    const double top = (double)((1u << AXIS_BITS) - 1);
    double scale[3];
    for (int i = 0; i < 3; ++i) { /* 0 for a flat, empty or overflowing extent: one code along it */
        const double e = khi[i] - klo[i];
        scale[i] = e > 0.0 && isfinite(e) ? top / e : 0.0;
        klo[i] = isfinite(klo[i]) ? klo[i] : 0.0;
    }
    scan_job jobs[GC_MAX_THREADS];
    for (int k = 0; k < parts; ++k) {
        scan_job *j = &jobs[k];
        j->mesh = mesh;
        j->f0 = part_start(n, k, parts, 1);
        j->f1 = part_start(n, k + 1, parts, 1);
        j->top = top;
        for (int i = 0; i < 3; ++i) {
            j->klo[i] = klo[i];
            j->scale[i] = scale[i];
        }
        j->codes = a;
        j->order = order;
    }
    run_parts(scan_part, jobs, sizeof *jobs, parts);
    int bad = 0;
    for (int i = 0; i < 3; ++i) {
        vlo[i] = INFINITY;
        vhi[i] = -INFINITY;
    }
    for (int k = 0; k < parts; ++k) {
        bad |= jobs[k].bad;
        for (int i = 0; i < 3; ++i) {
            vlo[i] = GC_MIN(vlo[i], jobs[k].lo[i]);
            vhi[i] = GC_MAX(vhi[i], jobs[k].hi[i]);
        }
    }
    if (bad) {
        if (sort) {
            scratch_free(b, counts, count_bytes);
            scratch_free(b, a, bytes);
            scratch_free(b, tmp, bytes);
        }
        st = gc_check_mesh(mesh, 0, NULL, NULL, b->err);
        if (st == GC_OK) { /* cannot happen: the two passes test the same conditions */
            gc_set_error(b->err, "the mesh has a face with a vertex index out of range or a vertex that is not finite");
            st = GC_ERR_ARGUMENT;
        }
        return st;
    }
    if (!sort) { /* the scan wrote the mesh's order */
        return GC_OK;
    }
    /* Each pass: the parts count their digits, each part's first slot for a digit
     * follows the earlier digits' items and the earlier parts' items of that
     * digit, and the parts scatter at once: the order one thread makes. */
    radix_job rj[GC_MAX_THREADS];
    for (int pass = 0; pass < PASSES; ++pass) {
        for (int k = 0; k < parts; ++k) {
            rj[k].src = a;
            rj[k].dst = pass + 1 < PASSES ? tmp : NULL;
            rj[k].order = order;
            rj[k].k0 = part_start(n, k, parts, 1);
            rj[k].k1 = part_start(n, k + 1, parts, 1);
            rj[k].shift = 32 + pass * RADIX_BITS;
            rj[k].count = counts + (size_t)k * RADIX_BUCKETS;
        }
        run_parts(radix_count_part, rj, sizeof *rj, parts);
        uint32_t next = 0;
        for (int d = 0; d < RADIX_BUCKETS; ++d) {
            for (int k = 0; k < parts; ++k) {
                const uint32_t c = rj[k].count[d];
                rj[k].count[d] = next;
                next += c;
            }
        }
        run_parts(radix_scatter_part, rj, sizeof *rj, parts);
        uint64_t *sw = a;
        a = tmp;
        tmp = sw;
    }
    scratch_free(b, counts, count_bytes);
    scratch_free(b, a, bytes);
    scratch_free(b, tmp, bytes);
    return GC_OK;
}

static gc_status check_params(const gc_build_params *p, char *err)
{
    if (p->intersector != GC_MOLLER_TRUMBORE && p->intersector != GC_WATERTIGHT) {
        gc_set_error(err, "unknown intersector %d", (int)p->intersector);
        return GC_ERR_ARGUMENT;
    }
    if (p->insertion != GC_INSERT_EXACT && p->insertion != GC_INSERT_BOUNDS) {
        gc_set_error(err, "unknown insertion mode %d", (int)p->insertion);
        return GC_ERR_ARGUMENT;
    }
    if (p->levels < 1 || p->levels > GC_MAX_LEVELS) {
        gc_set_error(err, "levels must be between 1 and %d, not %d", GC_MAX_LEVELS, p->levels);
        return GC_ERR_ARGUMENT;
    }
    for (int d = 1; d < p->levels; ++d) {
        if (!(p->level_scale[d] > 0.0) || !isfinite(p->level_scale[d]) ||
            !(p->level_exponent[d] > 0.0) || !isfinite(p->level_exponent[d])) {
            gc_set_error(err, "the rule for level %d needs a positive finite scale and exponent", d + 1);
            return GC_ERR_ARGUMENT;
        }
    }
    if (p->subgrid_resolutions2) {
        if (!p->subgrid_resolutions || p->levels < 3) {
            gc_set_error(err, "subgrid_resolutions2 needs subgrid_resolutions and levels >= 3");
            return GC_ERR_ARGUMENT;
        }
        /* rows the depth-1 subgrids' cells need (a bad resolution fails its own check later) */
        int64_t top = 1, rows = 0;
        for (int i = 0; i < 3; ++i) {
            if (p->resolution[i] < 1 || top > (int64_t)GC_MAX_CELLS / p->resolution[i]) {
                top = -1;
                break;
            }
            top *= p->resolution[i];
        }
        for (int64_t c = 0; c < top; ++c) {
            const int32_t *r = p->subgrid_resolutions + 3 * c;
            if (r[0] > 0 && r[1] > 0 && r[2] > 0) {
                double cells = (double)r[0] * (double)r[1] * (double)r[2];
                if (cells > (double)GC_MAX_CELLS || (double)rows + cells > (double)GC_MAX_CELLS) {
                    rows = -1;
                    break;
                }
                rows += (int64_t)r[0] * r[1] * r[2];
            }
        }
        if (top > 0 && rows >= 0 && rows != p->n_subgrid_resolutions2) {
            gc_set_error(err,
                         "subgrid_resolutions2 has %lld rows; the depth-1 subgrids have %lld cells, "
                         "one row each",
                         (long long)p->n_subgrid_resolutions2, (long long)rows);
            return GC_ERR_ARGUMENT;
        }
        if (top > 0 && rows < 0) {
            gc_set_error(err, "the depth-1 subgrids' cells overflow the grid's 32-bit cell offsets");
            return GC_ERR_OVERFLOW;
        }
    }
    if (p->threads < 0) {
        gc_set_error(err, "threads must be 0 or more (0 and 1: the calling thread only), not %d", p->threads);
        return GC_ERR_ARGUMENT;
    }
    if (p->rule_max_axis < 1) {
        gc_set_error(err, "rule_max_axis must be at least 1");
        return GC_ERR_ARGUMENT;
    }
    if (p->has_box) {
        for (int i = 0; i < 3; ++i) {
            if (!isfinite(p->box_lo[i]) || !isfinite(p->box_hi[i]) || !(p->box_hi[i] > p->box_lo[i])) {
                gc_set_error(err, "the grid box needs finite bounds with hi > lo on every axis");
                return GC_ERR_ARGUMENT;
            }
        }
    }
    return GC_OK;
}

/* Each reference's triangle and face index laid beside it: references [k0, k1), whole packs. */
typedef struct {
    gc_grid *g;
    const gc_mesh *mesh;
    int64_t k0, k1;
} fill_job;

static void fill_part(void *arg)
{
    fill_job *j = arg;
    gc_grid *g = j->g;
    const double *vert = j->mesh->vertices;
    const int64_t *faces = j->mesh->faces;
    for (int64_t k = j->k0; k < j->k1; ++k) {
        const uint32_t face = g->refs[k];
        prefetch_face(vert, faces, g->refs, k, j->k1);
        const int64_t *fv = faces + 3 * (int64_t)face;
        const double *v0 = vert + 3 * fv[0], *v1 = vert + 3 * fv[1], *v2 = vert + 3 * fv[2];
        gc_pack *pk = &g->ref_tris[k / GC_LANES];
        const int lane = (int)(k % GC_LANES);
        for (int i = 0; i < 3; ++i) {
            pk->c[i][lane] = v0[i];
            pk->c[3 + i][lane] = v1[i];
            pk->c[6 + i][lane] = v2[i];
        }
        pk->id[lane] = (int32_t)face;
    }
}

static gc_status build_grid(builder *b, const gc_mesh *mesh, gc_grid **out);

/* The cells' occupancy bits (gc_internal.h), 64 cells a word, from the finished records. */
static gc_status fill_occupancy(builder *b)
{
    gc_grid *g = b->g;
    const uint64_t words = GC_OCC_WORDS(g->n_cells);
    /* The walk's look-ahead reads the bit of the cell one step ahead before it knows that the
     * step stays in the node (gc_occupied): zero words of one layer of the largest node on
     * either side keep such a read in the array and make it an empty cell. */
    int64_t layer = 1;
    for (int64_t k = 0; k < g->n_nodes; ++k) {
        const int64_t cells = (int64_t)g->nodes[k].n[0] * (int64_t)g->nodes[k].n[1];
        layer = cells > layer ? cells : layer;
    }
    const uint64_t pad = GC_OCC_WORDS(layer) + 1;
    gc_status st = check_memory(b, (words + 2 * pad) * sizeof(uint64_t), "the cells' occupancy bits");
    if (st != GC_OK) {
        return st;
    }
    /* every word is written below */
    uint64_t *base = gc_big_alloc_raw((size_t)(words + 2 * pad) * sizeof(uint64_t), &g->occ_mapped, 0);
    if (!base) {
        gc_set_error(b->err, "out of memory for the occupancy bits of %lld cells", (long long)g->n_cells);
        return GC_ERR_NO_MEMORY;
    }
    memset(base, 0, (size_t)pad * sizeof(uint64_t));
    memset(base + pad + words, 0, (size_t)pad * sizeof(uint64_t));
    g->occ = base + pad;
    g->occ_pad = (int64_t)pad;
    const gc_cell *cells = g->cells;
    for (uint64_t w = 0; w < words; ++w) {
        const int64_t c0 = (int64_t)(w * 64);
        const int64_t n = g->n_cells - c0 < 64 ? g->n_cells - c0 : 64;
        uint64_t bits = 0;
        for (int64_t k = 0; k < n; ++k) {
            bits |= (uint64_t)(cells[c0 + k].count != 0) << k;
        }
        g->occ[w] = bits;
    }
    return GC_OK;
}

gc_status gc_grid_build(const gc_mesh *mesh, const gc_build_params *params, gc_grid **out, char *err)
{
    *out = NULL;
    gc_build_params p = params ? *params : gc_build_params_default();
    gc_status st = check_params(&p, err);
    if (st != GC_OK) {
        return st;
    }
    st = gc_check_mesh_shape(mesh, p.has_box, err);
    if (st != GC_OK) {
        return st;
    }
    builder b;
    memset(&b, 0, sizeof b);
    b.limit = p.memory_limit_bytes ? p.memory_limit_bytes : GC_DEFAULT_MEMORY_LIMIT_BYTES;
    b.p = &p;
    b.err = err;
    b.threads = p.threads < 1 ? 1 : (p.threads > GC_MAX_THREADS ? GC_MAX_THREADS : p.threads);
#ifndef GC_NO_THREADS
    if (b.threads > 1 && pthread_mutex_init(&b.lock, NULL) != 0) {
        b.threads = 1; /* no lock, no parts: one thread builds the same grid */
    }
#else
    b.threads = 1;
#endif
    st = build_grid(&b, mesh, out);
#ifndef GC_NO_THREADS
    if (b.threads > 1) {
        pthread_mutex_destroy(&b.lock);
    }
#endif
    return st;
}

static gc_status build_grid(builder *b, const gc_mesh *mesh, gc_grid **out)
{
    const gc_build_params *p = b->p;
    char *err = b->err;
    gc_status st;
    gc_grid *g = calloc(1, sizeof *g);
    if (!g) {
        gc_set_error(err, "out of memory");
        return GC_ERR_NO_MEMORY;
    }
    b->g = g;
    b->mesh = mesh;
    g->intersector = p->intersector;
    g->mailbox = p->mailbox != 0;
    g->n_tris = mesh->n_faces;

    /* the faces checked, their used vertices' bounds and their Morton order */
    double lo[3], hi[3], vlo[3] = {0.0, 0.0, 0.0}, vhi[3] = {0.0, 0.0, 0.0};
    uint32_t *prims = NULL;
    size_t prims_bytes = (size_t)(g->n_tris > 0 ? g->n_tris : 1) * sizeof(uint32_t);
    prims = scratch_alloc(b, prims_bytes, "the triangle list", &st);
    if (st == GC_OK && g->n_tris > 0) {
        st = scan_faces(b, mesh, vlo, vhi, prims);
    }
    if (st == GC_OK && p->has_box) {
        for (int i = 0; i < 3; ++i) {
            lo[i] = p->box_lo[i];
            hi[i] = p->box_hi[i];
        }
        /* the used vertices lie in the box if their bounds do; find the first that does not */
        int outside = 0;
        for (int i = 0; i < 3; ++i) {
            outside |= !(vlo[i] >= lo[i] && vhi[i] <= hi[i]);
        }
        for (int64_t k = 0; outside && st == GC_OK && k < 3 * mesh->n_faces; ++k) {
            const double *v = mesh->vertices + 3 * mesh->faces[k];
            for (int i = 0; i < 3; ++i) {
                if (!(v[i] >= lo[i] && v[i] <= hi[i])) {
                    gc_set_error(err, "vertex %lld lies outside the given grid box",
                                 (long long)mesh->faces[k]);
                    st = GC_ERR_ARGUMENT;
                    break;
                }
            }
        }
    } else if (st == GC_OK) { /* gc_check_mesh_shape refused a mesh without faces */
        for (int i = 0; i < 3; ++i) {
            lo[i] = vlo[i];
            hi[i] = vhi[i];
        }
        gc_widen_box(lo, hi);
    }
    /* Cell sizes and cell indices divide by the extent: an extent that overflows to
     * inf would turn them into NaN and the cell index into anything. */
    for (int i = 0; i < 3 && st == GC_OK; ++i) {
        if (!isfinite(hi[i] - lo[i])) {
            gc_set_error(err, "the grid box is too wide for double precision: its extent on axis %d overflows", i);
            st = GC_ERR_ARGUMENT;
        }
    }
    if (st == GC_OK) {
        st = check_resolution(b, p->resolution, 0);
    }
    if (st == GC_OK) {
        uint32_t top;
        st = build_node(b, prims, g->n_tris, lo, hi, p->resolution, 0, &top);
    }
    if (prims) {
        scratch_free(b, prims, prims_bytes);
    }
    if (st != GC_OK) {
        gc_grid_free(g);
        return st;
    }
    /* give back the doubling slack, then lay each reference's triangle beside it */
    if (g->n_refs > 0) {
        uint32_t *r = realloc(g->refs, (size_t)g->n_refs * sizeof(uint32_t));
        if (r) {
            g->refs = r;
        }
        b->cap_refs = g->n_refs;
    }
    /* grid_bytes has counted sizeof(gc_tri) a reference for the packs since the references
     * were sorted: only what the packs take beyond that is new */
    st = check_memory(b, GC_PACK_BYTES(g->n_refs) - (uint64_t)g->n_refs * sizeof(gc_tri),
                      "the per-reference triangles");
    if (st == GC_OK) {
        const size_t pack_bytes = (size_t)GC_PACK_BYTES(g->n_refs > 0 ? g->n_refs : 1);
        g->ref_tris = gc_big_alloc_raw(pack_bytes, &g->ref_tris_mapped, 0);
        if (!g->ref_tris) {
            gc_set_error(err, "out of memory copying %lld triangle references", (long long)g->n_refs);
            st = GC_ERR_NO_MEMORY;
        } else { /* the fill writes every reference's lane: the last pack's spare lanes read as zero */
            memset(&g->ref_tris[pack_bytes / sizeof(gc_pack) - 1], 0, sizeof(gc_pack));
        }
    }
    if (st != GC_OK) {
        gc_grid_free(g);
        return st;
    }
    {
        fill_job jobs[GC_MAX_THREADS];
        const int parts = parts_for(b, g->n_refs);
        for (int k = 0; k < parts; ++k) {
            jobs[k].g = g;
            jobs[k].mesh = mesh;
            jobs[k].k0 = part_start(g->n_refs, k, parts, GC_LANES);
            jobs[k].k1 = part_start(g->n_refs, k + 1, parts, GC_LANES);
        }
        run_parts(fill_part, jobs, sizeof *jobs, parts);
    }
    /* the packs hold all traversal reads: the build's references go */
    free(g->refs);
    g->refs = NULL;
    if (!g->cells_mapped) {
        g->cells = gc_big_move(g->cells, (size_t)g->n_cells * sizeof(gc_cell), &g->cells_mapped);
    }
    st = fill_occupancy(b);
    if (st != GC_OK) {
        gc_grid_free(g);
        return st;
    }
    *out = g;
    return GC_OK;
}
