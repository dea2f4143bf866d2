/* traverse.c - the traversal twins and the batch entry points.
 *
 * traverse_impl.h is compiled four times: {timed, instrumented} x {Moller-
 * Trumbore, watertight}.  The intersector is chosen when the grid is built, so
 * the inner loop never branches on it.  The timed twin contains no counter.
 * The watertight twins run the sign stage of the test over a pack of four
 * triangles: two lanes at a time with SSE2, all four at once with AVX2.  The
 * timed watertight twin is compiled both ways where the compiler can target
 * AVX2, and the host's CPU picks one when the first batch runs
 * (gc_traverse_isa); the instrumented twin uses SSE2.  Each lane's arithmetic
 * is the scalar test's, so hits and counts are the same on every path.
 */
#define _POSIX_C_SOURCE 199309L
#include "box.h"
#include "gc_internal.h"
#include "triangle.h"

#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef struct {
    double t;
    int32_t prim;
} gc_hit;

/* Mailbox: a per-triangle stamp of the last ray that tested it. */
typedef struct {
    uint32_t *stamp;
    int64_t n;
    uint32_t ray;
} gc_mail;

typedef struct {
    uint32_t steps, tests, subgrids, visits, changes;
} gc_counts;

static void gc_mail_next_ray(gc_mail *m)
{
    if (++m->ray == 0) { /* wrapped after 2^32 rays: forget every stamp */
        memset(m->stamp, 0, (size_t)m->n * sizeof(uint32_t));
        m->ray = 1;
    }
}

static gc_status mail_open(const gc_grid *g, gc_mail *m, gc_mail **use, char *err)
{
    *use = NULL;
    m->stamp = NULL;
    m->n = g->n_tris;
    m->ray = 0;
    if (!g->mailbox) {
        return GC_OK;
    }
    m->stamp = calloc((size_t)(g->n_tris > 0 ? g->n_tris : 1), sizeof(uint32_t));
    if (!m->stamp) {
        gc_set_error(err, "out of memory for the mailbox of %lld triangles", (long long)g->n_tris);
        return GC_ERR_NO_MEMORY;
    }
    *use = m;
    return GC_OK;
}

/* The walk's masked DDA step (traverse_impl.h) on x86-64 with SSE2. */
#if defined(__SSE2__) && defined(__x86_64__)
#include <emmintrin.h>
#define GC_MASKED_DDA 1
#else
#define GC_MASKED_DDA 0
#endif

/* The index of the lowest set bit of m (m != 0). */
static inline int gc_lowest_bit(int m)
{
#if defined(__GNUC__)
    return __builtin_ctz((unsigned)m);
#else
    int i = 0;
    while (!(m & 1)) {
        m >>= 1;
        ++i;
    }
    return i;
#endif
}

/* max(x, 0) then min(., top), as two selects the compiler cannot turn into
 * branches (x finite): which face a ray enters a node by is a coin toss. */
static inline double gc_clamp_cell(double x, double top)
{
#if GC_MASKED_DDA
    return _mm_cvtsd_f64(_mm_min_sd(_mm_max_sd(_mm_set_sd(x), _mm_setzero_pd()), _mm_set_sd(top)));
#else
    x = x > 0.0 ? x : 0.0;
    return x < top ? x : top;
#endif
}

#if defined(GC_HAVE_PACKED_WATERTIGHT)
#define GC_WT_SIMD 2
#else
#define GC_WT_SIMD 0
#endif
#define GC_TW_ATTR

#define GC_TW_COUNT 0
#define GC_TW_ISECT gc_isect_moller_trumbore
#define GC_TW_SIMD 0
#define GC_TW_NAME(x) x##_timed_mt
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_SIMD
#undef GC_TW_NAME

#define GC_TW_COUNT 0
#define GC_TW_ISECT gc_isect_watertight
#define GC_TW_SIMD GC_WT_SIMD
#define GC_TW_NAME(x) x##_timed_wt
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_SIMD
#undef GC_TW_NAME

#if defined(GC_HAVE_AVX2_WATERTIGHT)
#undef GC_TW_ATTR
#define GC_TW_ATTR GC_AVX2
#define GC_TW_COUNT 0
#define GC_TW_ISECT gc_isect_watertight
#define GC_TW_SIMD 4
#define GC_TW_NAME(x) x##_timed_wt_avx2
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_SIMD
#undef GC_TW_NAME
#undef GC_TW_ATTR
#define GC_TW_ATTR
#endif

#define GC_TW_COUNT 1
#define GC_TW_ISECT gc_isect_moller_trumbore
#define GC_TW_SIMD 0
#define GC_TW_NAME(x) x##_counted_mt
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_SIMD
#undef GC_TW_NAME

#define GC_TW_COUNT 1
#define GC_TW_ISECT gc_isect_watertight
#define GC_TW_SIMD GC_WT_SIMD
#define GC_TW_NAME(x) x##_counted_wt
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_SIMD
#undef GC_TW_NAME

/* Store one ray's hit (the mesh's face index, or -1) and return its share of the checksum. */
static inline double record_hit(const gc_hit *h, int64_t k, double *t_out, int32_t *prim_out)
{
    const int32_t id = h->prim;
    if (t_out) {
        t_out[k] = h->t;
        prim_out[k] = id;
    }
    return (id >= 0) ? h->t + (double)id : -1.0;
}

/* Which sign stage the timed watertight twin runs: GC_ISA_UNSET until the
 * first batch (or gc_traverse_set_isa) decides. */
enum { GC_ISA_UNSET = -1, GC_ISA_SSE2 = 0, GC_ISA_AVX2 = 1 };
static int gc_isa = GC_ISA_UNSET;

static int host_has_avx2(void)
{
#if defined(GC_HAVE_AVX2_WATERTIGHT)
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") != 0;
#else
    return 0;
#endif
}

static int isa_in_use(void)
{
    if (gc_isa == GC_ISA_UNSET) {
        gc_isa = host_has_avx2() ? GC_ISA_AVX2 : GC_ISA_SSE2;
    }
    return gc_isa;
}

const char *gc_traverse_isa(void)
{
#if GC_WT_SIMD
    return isa_in_use() == GC_ISA_AVX2 ? "avx2" : "sse2";
#else
    return "scalar";
#endif
}

gc_status gc_traverse_set_isa(const char *isa, char *err)
{
    if (!isa) {
        gc_set_error(err, "no instruction set named");
        return GC_ERR_ARGUMENT;
    }
    if (!strcmp(isa, "auto")) {
        gc_isa = GC_ISA_UNSET;
        (void)isa_in_use();
        return GC_OK;
    }
#if GC_WT_SIMD
    if (!strcmp(isa, "sse2")) {
        gc_isa = GC_ISA_SSE2;
        return GC_OK;
    }
    if (!strcmp(isa, "avx2")) {
        if (!host_has_avx2()) {
            gc_set_error(err, "this %s does not have AVX2",
#if defined(GC_HAVE_AVX2_WATERTIGHT)
                         "CPU"
#else
                         "build"
#endif
            );
            return GC_ERR_ARGUMENT;
        }
        gc_isa = GC_ISA_AVX2;
        return GC_OK;
    }
    gc_set_error(err, "unknown instruction set '%.32s' (auto, sse2 or avx2)", isa);
#else
    gc_set_error(err, "unknown instruction set '%.32s' (this build has only auto)", isa);
#endif
    return GC_ERR_ARGUMENT;
}

#if defined(GC_HAVE_AVX2_WATERTIGHT)
/* The timed watertight twin's batch loop on AVX2: compiled for AVX2 like the walk, so
 * the ray's preparation, its box clip (trace_timed_wt_avx2, inlined) and the call into
 * the walk are AVX2 code in one function, with no call from code built for SSE2. */
GC_AVX2 static double trace_batch_timed_avx2(const gc_grid *g, int64_t n, const double *orig,
                                             const double *dir, double *t_out, int32_t *prim_out,
                                             gc_mail *mail)
{
    double sum = 0.0;
    wray_timed_wt_avx2 w;
    gc_hit h;
    for (int64_t k = 0; k < n; ++k) {
#if defined(GC_HAVE_AVX2_RAY)
        gc_ray_prepare_avx2(&w.ray, orig + 3 * k, dir + 3 * k);
#else
        gc_ray_prepare(&w.ray, orig + 3 * k, dir + 3 * k); /* 32-bit x86: the scalar preparation */
#endif
        trace_timed_wt_avx2(g, &w, &h, mail);
        sum += record_hit(&h, k, t_out, prim_out);
    }
    return sum;
}
#endif

/* Trace rays [0, n) with the timed twin; returns the checksum of the results.
 * The intersector and the instruction set are chosen once, outside the loop. */
static double trace_batch_timed(const gc_grid *g, int64_t n, const double *orig, const double *dir,
                                double *t_out, int32_t *prim_out, gc_mail *mail)
{
    double sum = 0.0;
    gc_hit h;
    if (g->intersector == GC_WATERTIGHT) {
#if defined(GC_HAVE_AVX2_WATERTIGHT)
        if (isa_in_use() == GC_ISA_AVX2) {
            return trace_batch_timed_avx2(g, n, orig, dir, t_out, prim_out, mail);
        }
#endif
        wray_timed_wt w;
        for (int64_t k = 0; k < n; ++k) {
            gc_ray_prepare(&w.ray, orig + 3 * k, dir + 3 * k);
            trace_timed_wt(g, &w, &h, mail);
            sum += record_hit(&h, k, t_out, prim_out);
        }
    } else {
        wray_timed_mt w;
        for (int64_t k = 0; k < n; ++k) {
            gc_ray_prepare(&w.ray, orig + 3 * k, dir + 3 * k);
            trace_timed_mt(g, &w, &h, mail);
            sum += record_hit(&h, k, t_out, prim_out);
        }
    }
    return sum;
}

gc_status gc_intersect(const gc_grid *g, int64_t n, const double *origins, const double *directions,
                       double *t, int32_t *prim, char *err)
{
    gc_status st = gc_check_rays(n, origins, directions, err);
    if (st != GC_OK) {
        return st;
    }
    if (n > 0 && (!t || !prim)) {
        gc_set_error(err, "output arrays are missing");
        return GC_ERR_ARGUMENT;
    }
    gc_mail m, *mail;
    st = mail_open(g, &m, &mail, err);
    if (st != GC_OK) {
        return st;
    }
    (void)trace_batch_timed(g, n, origins, directions, t, prim, mail);
    free(m.stamp);
    return GC_OK;
}

gc_status gc_count(const gc_grid *g, int64_t n, const double *origins, const double *directions,
                   double *t, int32_t *prim, uint32_t *steps, uint32_t *tests, uint32_t *subgrids,
                   uint32_t *visits, uint32_t *changes, char *err)
{
    gc_status st = gc_check_rays(n, origins, directions, err);
    if (st != GC_OK) {
        return st;
    }
    gc_mail m, *mail;
    st = mail_open(g, &m, &mail, err);
    if (st != GC_OK) {
        return st;
    }
    wray_counted_wt wt;
    wray_counted_mt mt;
    gc_hit h;
    for (int64_t k = 0; k < n; ++k) {
        gc_counts cnt = {0, 0, 0, 0, 0};
        if (g->intersector == GC_WATERTIGHT) {
            gc_ray_prepare(&wt.ray, origins + 3 * k, directions + 3 * k);
            trace_counted_wt(g, &wt, &h, mail, &cnt);
        } else {
            gc_ray_prepare(&mt.ray, origins + 3 * k, directions + 3 * k);
            trace_counted_mt(g, &mt, &h, mail, &cnt);
        }
        if (t) {
            t[k] = h.t;
        }
        if (prim) {
            prim[k] = h.prim;
        }
        if (steps) {
            steps[k] = cnt.steps;
        }
        if (tests) {
            tests[k] = cnt.tests;
        }
        if (subgrids) {
            subgrids[k] = cnt.subgrids;
        }
        if (visits) {
            visits[k] = cnt.visits;
        }
        if (changes) {
            changes[k] = cnt.changes;
        }
    }
    free(m.stamp);
    return GC_OK;
}

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

gc_status gc_bench_intersect(const gc_grid *g, int64_t n, const double *origins,
                             const double *directions, int64_t loops, int64_t *elapsed_ns,
                             double *checksum, char *err)
{
    gc_status st = gc_check_rays(n, origins, directions, err);
    if (st != GC_OK) {
        return st;
    }
    if (loops < 1) {
        gc_set_error(err, "loops must be at least 1, not %lld", (long long)loops);
        return GC_ERR_ARGUMENT;
    }
    gc_mail m, *mail;
    st = mail_open(g, &m, &mail, err);
    if (st != GC_OK) {
        return st;
    }
    double sum = 0.0;
    const int64_t start = now_ns();
    for (int64_t l = 0; l < loops; ++l) {
        sum += trace_batch_timed(g, n, origins, directions, NULL, NULL, mail);
    }
    const int64_t stop = now_ns();
    free(m.stamp);
    *elapsed_ns = stop - start;
    *checksum = sum;
    return GC_OK;
}
