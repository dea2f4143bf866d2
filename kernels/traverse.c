/* traverse.c - the traversal twins and the batch entry points.
 *
 * traverse_impl.h is compiled four times: {timed, instrumented} x {Moller-
 * Trumbore, watertight}.  The intersector is chosen when the grid is built, so
 * the inner loop never branches on it.  The timed twin contains no counter.
 * On SSE2 the watertight twins test a cell's triangles two at a time
 * (gc_isect_watertight_signs2); the results are those of one at a time.
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
    uint32_t steps, tests, subgrids;
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

#if defined(GC_HAVE_PACKED_WATERTIGHT)
#define GC_WT_PACKED 1
#else
#define GC_WT_PACKED 0
#endif

#define GC_TW_COUNT 0
#define GC_TW_ISECT gc_isect_moller_trumbore
#define GC_TW_PACKED 0
#define GC_TW_NAME(x) x##_timed_mt
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_PACKED
#undef GC_TW_NAME

#define GC_TW_COUNT 0
#define GC_TW_ISECT gc_isect_watertight
#define GC_TW_PACKED GC_WT_PACKED
#define GC_TW_NAME(x) x##_timed_wt
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_PACKED
#undef GC_TW_NAME

#define GC_TW_COUNT 1
#define GC_TW_ISECT gc_isect_moller_trumbore
#define GC_TW_PACKED 0
#define GC_TW_NAME(x) x##_counted_mt
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_PACKED
#undef GC_TW_NAME

#define GC_TW_COUNT 1
#define GC_TW_ISECT gc_isect_watertight
#define GC_TW_PACKED GC_WT_PACKED
#define GC_TW_NAME(x) x##_counted_wt
#include "traverse_impl.h"
#undef GC_TW_COUNT
#undef GC_TW_ISECT
#undef GC_TW_PACKED
#undef GC_TW_NAME

/* Store one ray's hit (as the mesh's face index) and return its share of the checksum. */
static inline double record_hit(const gc_grid *g, const gc_hit *h, int64_t k, double *t_out, int32_t *prim_out)
{
    const int32_t id = h->prim >= 0 ? g->tri_id[h->prim] : -1;
    if (t_out) {
        t_out[k] = h->t;
        prim_out[k] = id;
    }
    return (id >= 0) ? h->t + (double)id : -1.0;
}

/* Trace rays [0, n) with the timed twin; returns the checksum of the results.
 * The intersector is chosen once, outside the loop. */
static double trace_batch_timed(const gc_grid *g, int64_t n, const double *orig, const double *dir,
                                double *t_out, int32_t *prim_out, gc_mail *mail)
{
    double sum = 0.0;
    gc_ray r;
    gc_hit h;
    if (g->intersector == GC_WATERTIGHT) {
        for (int64_t k = 0; k < n; ++k) {
            gc_ray_prepare(&r, orig + 3 * k, dir + 3 * k);
            trace_timed_wt(g, &r, &h, mail);
            sum += record_hit(g, &h, k, t_out, prim_out);
        }
    } else {
        for (int64_t k = 0; k < n; ++k) {
            gc_ray_prepare(&r, orig + 3 * k, dir + 3 * k);
            trace_timed_mt(g, &r, &h, mail);
            sum += record_hit(g, &h, k, t_out, prim_out);
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
                   char *err)
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
    gc_ray r;
    gc_hit h;
    for (int64_t k = 0; k < n; ++k) {
        gc_counts cnt = {0, 0, 0};
        gc_ray_prepare(&r, origins + 3 * k, directions + 3 * k);
        if (g->intersector == GC_WATERTIGHT) {
            trace_counted_wt(g, &r, &h, mail, &cnt);
        } else {
            trace_counted_mt(g, &r, &h, mail, &cnt);
        }
        if (t) {
            t[k] = h.t;
        }
        if (prim) {
            prim[k] = h.prim >= 0 ? g->tri_id[h.prim] : -1;
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
