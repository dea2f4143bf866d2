/* stats.c - the scene sums of the cost model in one pass over the triangles,
 * and the watertightness test (every edge shared by exactly two faces).
 *
 * These mirror models/stats.py (the numpy reference, which defines them) term by
 * term and in the same floating-point order per triangle; only the order of the
 * sums over triangles differs, so results agree to rounding.  They exist for
 * speed: one cache-friendly pass instead of numpy temporaries.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "gridcal.h"

/* models/stats.py DEGENERATE_REL_AREA: degenerate when 2 area <= this * longest_edge^2. */
#define DEGENERATE_REL_AREA 1e-12

/* min and max without fmin's NaN rules (inputs are finite): plain compares, inlined. */
static double lesser(double a, double b) { return b < a ? b : a; }
static double greater(double a, double b) { return b > a ? b : a; }

static int valid_faces(const gc_mesh *mesh, char *err)
{
    for (int64_t i = 0; i < 3 * mesh->n_faces; ++i) {
        if (mesh->faces[i] < 0 || mesh->faces[i] >= mesh->n_vertices) {
            if (err) {
                snprintf(err, GC_ERROR_LEN, "face %lld has a vertex index out of range [0, %lld)",
                         (long long)(i / 3), (long long)mesh->n_vertices);
            }
            return 0;
        }
    }
    return 1;
}

gc_status gc_mesh_sums_compute(const gc_mesh *mesh, int64_t ar_stride,
                               double *ar_out, int64_t *n_ar, gc_mesh_sums *out, char *err)
{
    if (!mesh || !out || ar_stride < 1 || (ar_out && !n_ar)) {
        if (err) {
            snprintf(err, GC_ERROR_LEN, "gc_mesh_sums_compute: bad arguments");
        }
        return GC_ERR_ARGUMENT;
    }
    if (!valid_faces(mesh, err)) {
        return GC_ERR_ARGUMENT;
    }
    /* Accumulate in locals (the output could alias the vertices as far as the compiler knows). */
    double lo_b[3] = {INFINITY, INFINITY, INFINITY}, hi_b[3] = {-INFINITY, -INFINITY, -INFINITY};
    double e1[3] = {0, 0, 0}, e2[3] = {0, 0, 0}, per[3] = {0, 0, 0}, pair[3] = {0, 0, 0};
    double triple = 0.0, area_sum = 0.0, vol6 = 0.0;
    int64_t n_good = 0, n_sample = 0, until_sample = 0; /* triangles until the next sampled one */
    const double *v = mesh->vertices;
    /* reference point of the enclosed volume: the centre of all vertices' bounds */
    double vlo[3] = {INFINITY, INFINITY, INFINITY}, vhi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (int64_t i = 0; i < mesh->n_vertices; ++i) {
        for (int a = 0; a < 3; ++a) {
            vlo[a] = lesser(vlo[a], v[3 * i + a]);
            vhi[a] = greater(vhi[a], v[3 * i + a]);
        }
    }
    const double c0 = 0.5 * (vlo[0] + vhi[0]), c1 = 0.5 * (vlo[1] + vhi[1]), c2 = 0.5 * (vlo[2] + vhi[2]);
    for (int64_t t = 0; t < mesh->n_faces; ++t) {
        const double *p0 = v + 3 * mesh->faces[3 * t];
        const double *p1 = v + 3 * mesh->faces[3 * t + 1];
        const double *p2 = v + 3 * mesh->faces[3 * t + 2];
        double ext[3], u[3], w[3], e[3], cross[3];
        for (int a = 0; a < 3; ++a) {
            double lo = lesser(lesser(p0[a], p1[a]), p2[a]);
            double hi = greater(greater(p0[a], p1[a]), p2[a]);
            lo_b[a] = lesser(lo_b[a], lo);
            hi_b[a] = greater(hi_b[a], hi);
            ext[a] = hi - lo;
            e1[a] += ext[a];
            u[a] = p1[a] - p0[a];
            w[a] = p2[a] - p0[a];
            e[a] = p2[a] - p1[a];
        }
        cross[0] = u[1] * w[2] - u[2] * w[1];
        cross[1] = u[2] * w[0] - u[0] * w[2];
        cross[2] = u[0] * w[1] - u[1] * w[0];
        double area = 0.5 * sqrt(cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]);
        /* squared edge components, edges in the order u = p1-p0, e = p2-p1, w = p2-p0 */
        double su[3] = {u[0] * u[0], u[1] * u[1], u[2] * u[2]};
        double se[3] = {e[0] * e[0], e[1] * e[1], e[2] * e[2]};
        double sw[3] = {w[0] * w[0], w[1] * w[1], w[2] * w[2]};
        double tu = su[0] + su[1] + su[2], te = se[0] + se[1] + se[2], tw = sw[0] + sw[1] + sw[2];
        for (int a = 0; a < 3; ++a) {
            e2[a] += 0.5 * fabs(cross[a]);
            /* perimeter projected along axis a: each edge without its component a */
            per[a] += sqrt(greater(tu - su[a], 0.0)) + sqrt(greater(te - se[a], 0.0)) +
                      sqrt(greater(tw - sw[a], 0.0));
        }
        pair[0] += ext[1] * ext[2];
        pair[1] += ext[2] * ext[0];
        pair[2] += ext[0] * ext[1];
        triple += ext[0] * ext[1] * ext[2];
        area_sum += area;
        vol6 += (p0[0] - c0) * cross[0] + (p0[1] - c1) * cross[1] + (p0[2] - c2) * cross[2];
        double longest = greater(greater(tu, te), tw);
        int good = 2.0 * area > DEGENERATE_REL_AREA * longest;
        n_good += good;
        if (until_sample-- == 0) { /* every ar_stride-th triangle, without a division */
            until_sample = ar_stride - 1;
            if (ar_out && good) {
                ar_out[n_sample++] = longest / (2.0 * area);
            }
        }
    }
    for (int a = 0; a < 3; ++a) {
        out->box_lo[a] = lo_b[a];
        out->box_hi[a] = hi_b[a];
        out->e1[a] = e1[a];
        out->e2[a] = e2[a];
        out->perimeters[a] = per[a];
        out->pair[a] = pair[a];
    }
    out->triple = triple;
    out->area = area_sum;
    out->vol6 = vol6;
    out->n_good = n_good;
    if (n_ar) {
        *n_ar = n_sample;
    }
    return GC_OK;
}

/* -- watertightness ------------------------------------------------------------- */

/* Bits of a coordinate with -0.0 folded onto +0.0, so equal positions hash equal. */
static uint64_t coord_bits(double x)
{
    uint64_t b;
    x += 0.0;
    memcpy(&b, &x, sizeof b);
    return b;
}

static uint64_t splitmix(uint64_t x)
{
    x ^= x >> 30;
    x *= 0xBF58476D1CE4E5B9ull;
    x ^= x >> 27;
    x *= 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}

static int same_position(const double *a, const double *b)
{
    return a[0] == b[0] && a[1] == b[1] && a[2] == b[2]; /* -0.0 == +0.0; no NaN here */
}

/* id[i] = the first vertex at the same position as vertex i (open addressing). */
static gc_status merge_positions(const double *v, int64_t nv, int64_t *id)
{
    uint64_t cap = 16;
    while (cap < 2u * (uint64_t)nv) {
        cap <<= 1;
    }
    int64_t *table = malloc(cap * sizeof *table);
    if (!table) {
        return GC_ERR_NO_MEMORY;
    }
    for (uint64_t i = 0; i < cap; ++i) {
        table[i] = -1;
    }
    for (int64_t i = 0; i < nv; ++i) {
        const double *p = v + 3 * i;
        uint64_t h = splitmix(coord_bits(p[0]) + 0x9E3779B97F4A7C15ull);
        h = splitmix(h ^ coord_bits(p[1]));
        h = splitmix(h ^ coord_bits(p[2]));
        for (uint64_t s = h & (cap - 1);; s = (s + 1) & (cap - 1)) {
            if (table[s] < 0) {
                table[s] = i;
                id[i] = i;
                break;
            }
            if (same_position(v + 3 * table[s], p)) {
                id[i] = table[s];
                break;
            }
        }
    }
    free(table);
    return GC_OK;
}

static int cmp_i64(const void *a, const void *b)
{
    int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

gc_status gc_mesh_watertight(const gc_mesh *mesh, int *watertight, char *err)
{
    if (!mesh || !watertight) {
        if (err) {
            snprintf(err, GC_ERROR_LEN, "gc_mesh_watertight: bad arguments");
        }
        return GC_ERR_ARGUMENT;
    }
    if (!valid_faces(mesh, err)) {
        return GC_ERR_ARGUMENT;
    }
    *watertight = 0;
    int64_t nv = mesh->n_vertices, ne = 3 * mesh->n_faces;
    if (ne == 0) {
        return GC_OK;
    }
    int64_t *id = malloc((size_t)nv * sizeof *id);
    int64_t *start = calloc((size_t)nv + 1, sizeof *start);
    int64_t *other = malloc((size_t)ne * sizeof *other);
    gc_status st = (id && start && other) ? merge_positions(mesh->vertices, nv, id) : GC_ERR_NO_MEMORY;
    if (st == GC_OK) {
        /* Counting sort of the undirected edges by their smaller merged endpoint. */
        const int64_t *f = mesh->faces;
        for (int64_t i = 0; i < ne; ++i) {
            int64_t a = id[f[i]], b = id[f[i - i % 3 + (i % 3 + 1) % 3]];
            start[(a < b ? a : b) + 1]++;
        }
        for (int64_t i = 0; i < nv; ++i) {
            start[i + 1] += start[i];
        }
        for (int64_t i = 0; i < ne; ++i) {
            int64_t a = id[f[i]], b = id[f[i - i % 3 + (i % 3 + 1) % 3]];
            int64_t lo = a < b ? a : b, hi = a < b ? b : a;
            other[start[lo]++] = hi;
        }
        /* start[lo] is now the end of lo's bucket; every partner must occur exactly twice. */
        int ok = 1;
        for (int64_t lo = 0, begin = 0; lo < nv && ok; begin = start[lo], ++lo) {
            int64_t n = start[lo] - begin;
            int64_t *b = other + begin;
            if (n % 2) {
                ok = 0;
                break;
            }
            if (n <= 16) {
                for (int64_t i = 1; i < n; ++i) { /* insertion sort: buckets are small */
                    int64_t x = b[i], j = i;
                    for (; j > 0 && b[j - 1] > x; --j) {
                        b[j] = b[j - 1];
                    }
                    b[j] = x;
                }
            } else {
                qsort(b, (size_t)n, sizeof *b, cmp_i64);
            }
            for (int64_t i = 0; i < n; i += 2) {
                if (b[i] != b[i + 1] || (i + 2 < n && b[i + 2] == b[i])) {
                    ok = 0;
                    break;
                }
            }
        }
        *watertight = ok;
    } else if (err) {
        snprintf(err, GC_ERROR_LEN, "out of memory testing watertightness of %lld faces",
                 (long long)mesh->n_faces);
    }
    free(id);
    free(start);
    free(other);
    return st;
}
