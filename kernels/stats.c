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

/* SSE2 (every x86-64) does the pass two triangles at a time; elsewhere, or with
 * GC_STATS_NO_SIMD defined (the C tests build both), one at a time. */
#if defined(__SSE2__) && !defined(GC_STATS_NO_SIMD)
#define GC_STATS_SIMD 1
#include <emmintrin.h>
#endif

/* models/stats.py DEGENERATE_REL_AREA: degenerate when 2 area <= this * longest_edge^2. */
#define DEGENERATE_REL_AREA 1e-12

#if defined(__GNUC__) || defined(__clang__)
#define GC_PREFETCH(p) __builtin_prefetch(p)
#define GC_PREFETCH_WRITE(p) __builtin_prefetch(p, 1)
#else
#define GC_PREFETCH(p) ((void)(p))
#define GC_PREFETCH_WRITE(p) ((void)(p))
#endif

/* min and max without fmin's NaN rules (inputs are finite): plain compares, inlined. */
static double lesser(double a, double b) { return b < a ? b : a; }
static double greater(double a, double b) { return b > a ? b : a; }

static void report_bad_face(const gc_mesh *mesh, int64_t t, char *err)
{
    if (err) {
        snprintf(err, GC_ERROR_LEN, "face %lld has a vertex index out of range [0, %lld)", (long long)t,
                 (long long)mesh->n_vertices);
    }
}

/* Nonzero when face t refers to a vertex outside [0, n_vertices). */
static int bad_face(const gc_mesh *mesh, int64_t t)
{
    const uint64_t nv = (uint64_t)mesh->n_vertices; /* a negative index wraps to a huge one */
    const int64_t *f = mesh->faces + 3 * t;
    return ((uint64_t)f[0] >= nv) | ((uint64_t)f[1] >= nv) | ((uint64_t)f[2] >= nv);
}

/* Triangles ahead whose corners are prefetched: a mesh's vertex order need not
 * follow its face order, and then the gathers miss the caches. */
#define PREFETCH_AHEAD 16

/* Prefetch the corners of face t (when it exists and its indices are in range).  A
 * macro: GCC judges a function holding only prefetches free of effects and drops
 * the call. */
#define PREFETCH_CORNERS(mesh, t)                                                                 \
    do {                                                                                          \
        if ((t) < (mesh)->n_faces) {                                                              \
            const int64_t *q_ = (mesh)->faces + 3 * (t);                                          \
            for (int j_ = 0; j_ < 3; ++j_) {                                                      \
                if ((uint64_t)q_[j_] < (uint64_t)(mesh)->n_vertices) {                            \
                    GC_PREFETCH((mesh)->vertices + 3 * q_[j_]);                                   \
                }                                                                                 \
            }                                                                                     \
        }                                                                                         \
    } while (0)

/* The running sums of the pass (one set per SIMD lane, one for the scalar path). */
typedef struct {
    double lo_b[3], hi_b[3], e1[3], e2[3], per[3], pair[3];
    double triple, area, vol6;
} sums_acc;

static void sums_acc_init(sums_acc *s)
{
    for (int a = 0; a < 3; ++a) {
        s->lo_b[a] = INFINITY;
        s->hi_b[a] = -INFINITY;
        s->e1[a] = s->e2[a] = s->per[a] = s->pair[a] = 0.0;
    }
    s->triple = s->area = s->vol6 = 0.0;
}

/* Add triangle (p0, p1, p2) to *s; c is the volume's reference point.  Returns the
 * squared longest edge and sets *area2 to twice the area. */
static double add_triangle(sums_acc *s, const double *p0, const double *p1, const double *p2, const double *c,
                           double *area2)
{
    double ext[3], u[3], w[3], e[3], cross[3];
    for (int a = 0; a < 3; ++a) {
        double lo = lesser(lesser(p0[a], p1[a]), p2[a]);
        double hi = greater(greater(p0[a], p1[a]), p2[a]);
        s->lo_b[a] = lesser(s->lo_b[a], lo);
        s->hi_b[a] = greater(s->hi_b[a], hi);
        ext[a] = hi - lo;
        s->e1[a] += ext[a];
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
        s->e2[a] += 0.5 * fabs(cross[a]);
        /* perimeter projected along axis a: each edge without its component a */
        s->per[a] += sqrt(greater(tu - su[a], 0.0)) + sqrt(greater(te - se[a], 0.0)) +
                     sqrt(greater(tw - sw[a], 0.0));
    }
    s->pair[0] += ext[1] * ext[2];
    s->pair[1] += ext[2] * ext[0];
    s->pair[2] += ext[0] * ext[1];
    s->triple += ext[0] * ext[1] * ext[2];
    s->area += area;
    s->vol6 += (p0[0] - c[0]) * cross[0] + (p0[1] - c[1]) * cross[1] + (p0[2] - c[2]) * cross[2];
    *area2 = 2.0 * area;
    return greater(greater(tu, te), tw);
}

/* Sampling and degenerate counting of one triangle, in triangle order. */
typedef struct {
    int64_t stride, until_sample, n_sample, n_good; /* until_sample: triangles until the next sampled one */
    double *ar_out;
} shape_tally;

static void tally_shape(shape_tally *k, double longest, double area2)
{
    int good = area2 > DEGENERATE_REL_AREA * longest;
    k->n_good += good;
    if (k->until_sample-- == 0) { /* every stride-th triangle, without a division */
        k->until_sample = k->stride - 1;
        if (k->ar_out && good) {
            k->ar_out[k->n_sample++] = longest / area2;
        }
    }
}

#ifdef GC_STATS_SIMD
/* Two triangles at a time, one per SSE2 lane.  Every lane does the operations of
 * add_triangle in the same order (IEEE operations, no contraction), so each
 * triangle's terms are bit-identical to the scalar path; only the order of the sums
 * over triangles differs (each lane sums every other triangle).  min/max keep the
 * operand order of lesser/greater: _mm_min_pd(b, a) == lesser(a, b). */
typedef struct {
    __m128d lo_b[3], hi_b[3], e1[3], e2[3], per[3], pair[3];
    __m128d triple, area, vol6;
} sums_acc2;

static double lane_sum(__m128d x)
{
    return _mm_cvtsd_f64(x) + _mm_cvtsd_f64(_mm_unpackhi_pd(x, x));
}

/* Fold the two lanes of *v into *s (lane 0, then lane 1, then the scalar sums). */
static void sums_acc2_fold(const sums_acc2 *v, sums_acc *s)
{
    for (int a = 0; a < 3; ++a) {
        double lo[2], hi[2];
        _mm_storeu_pd(lo, v->lo_b[a]);
        _mm_storeu_pd(hi, v->hi_b[a]);
        s->lo_b[a] = lesser(lesser(lo[0], lo[1]), s->lo_b[a]);
        s->hi_b[a] = greater(greater(hi[0], hi[1]), s->hi_b[a]);
        s->e1[a] = lane_sum(v->e1[a]) + s->e1[a];
        s->e2[a] = lane_sum(v->e2[a]) + s->e2[a];
        s->per[a] = lane_sum(v->per[a]) + s->per[a];
        s->pair[a] = lane_sum(v->pair[a]) + s->pair[a];
    }
    s->triple = lane_sum(v->triple) + s->triple;
    s->area = lane_sum(v->area) + s->area;
    s->vol6 = lane_sum(v->vol6) + s->vol6;
}

static __m128d sqrt_nonneg(__m128d x)
{
    return _mm_sqrt_pd(_mm_max_pd(_mm_setzero_pd(), x)); /* sqrt(greater(x, 0.0)) */
}

/* Triangles t and t + 1 (their indices already checked). */
static void add_triangle_pair(sums_acc2 *s, shape_tally *k, const double *v, const int64_t *f, const double *c)
{
    const double *a0 = v + 3 * f[0], *a1 = v + 3 * f[1], *a2 = v + 3 * f[2];
    const double *b0 = v + 3 * f[3], *b1 = v + 3 * f[4], *b2 = v + 3 * f[5];
    __m128d p0[3], u[3], w[3], e[3], ext[3], cross[3], su[3], se[3], sw[3];
    for (int a = 0; a < 3; ++a) {
        __m128d q0 = _mm_loadh_pd(_mm_load_sd(a0 + a), b0 + a);
        __m128d q1 = _mm_loadh_pd(_mm_load_sd(a1 + a), b1 + a);
        __m128d q2 = _mm_loadh_pd(_mm_load_sd(a2 + a), b2 + a);
        __m128d lo = _mm_min_pd(q2, _mm_min_pd(q1, q0));
        __m128d hi = _mm_max_pd(q2, _mm_max_pd(q1, q0));
        s->lo_b[a] = _mm_min_pd(lo, s->lo_b[a]);
        s->hi_b[a] = _mm_max_pd(hi, s->hi_b[a]);
        ext[a] = _mm_sub_pd(hi, lo);
        s->e1[a] = _mm_add_pd(s->e1[a], ext[a]);
        p0[a] = q0;
        u[a] = _mm_sub_pd(q1, q0);
        w[a] = _mm_sub_pd(q2, q0);
        e[a] = _mm_sub_pd(q2, q1);
    }
    cross[0] = _mm_sub_pd(_mm_mul_pd(u[1], w[2]), _mm_mul_pd(u[2], w[1]));
    cross[1] = _mm_sub_pd(_mm_mul_pd(u[2], w[0]), _mm_mul_pd(u[0], w[2]));
    cross[2] = _mm_sub_pd(_mm_mul_pd(u[0], w[1]), _mm_mul_pd(u[1], w[0]));
    const __m128d half = _mm_set1_pd(0.5);
    __m128d cc = _mm_add_pd(_mm_add_pd(_mm_mul_pd(cross[0], cross[0]), _mm_mul_pd(cross[1], cross[1])),
                            _mm_mul_pd(cross[2], cross[2]));
    __m128d area = _mm_mul_pd(half, _mm_sqrt_pd(cc));
    for (int a = 0; a < 3; ++a) {
        su[a] = _mm_mul_pd(u[a], u[a]);
        se[a] = _mm_mul_pd(e[a], e[a]);
        sw[a] = _mm_mul_pd(w[a], w[a]);
    }
    __m128d tu = _mm_add_pd(_mm_add_pd(su[0], su[1]), su[2]);
    __m128d te = _mm_add_pd(_mm_add_pd(se[0], se[1]), se[2]);
    __m128d tw = _mm_add_pd(_mm_add_pd(sw[0], sw[1]), sw[2]);
    const __m128d sign = _mm_set1_pd(-0.0);
    for (int a = 0; a < 3; ++a) {
        s->e2[a] = _mm_add_pd(s->e2[a], _mm_mul_pd(half, _mm_andnot_pd(sign, cross[a])));
        __m128d pa = _mm_add_pd(_mm_add_pd(sqrt_nonneg(_mm_sub_pd(tu, su[a])), sqrt_nonneg(_mm_sub_pd(te, se[a]))),
                                sqrt_nonneg(_mm_sub_pd(tw, sw[a])));
        s->per[a] = _mm_add_pd(s->per[a], pa);
    }
    s->pair[0] = _mm_add_pd(s->pair[0], _mm_mul_pd(ext[1], ext[2]));
    s->pair[1] = _mm_add_pd(s->pair[1], _mm_mul_pd(ext[2], ext[0]));
    s->pair[2] = _mm_add_pd(s->pair[2], _mm_mul_pd(ext[0], ext[1]));
    s->triple = _mm_add_pd(s->triple, _mm_mul_pd(_mm_mul_pd(ext[0], ext[1]), ext[2]));
    s->area = _mm_add_pd(s->area, area);
    __m128d vol = _mm_add_pd(_mm_add_pd(_mm_mul_pd(_mm_sub_pd(p0[0], _mm_set1_pd(c[0])), cross[0]),
                                        _mm_mul_pd(_mm_sub_pd(p0[1], _mm_set1_pd(c[1])), cross[1])),
                             _mm_mul_pd(_mm_sub_pd(p0[2], _mm_set1_pd(c[2])), cross[2]));
    s->vol6 = _mm_add_pd(s->vol6, vol);
    double longest[2], area2[2];
    _mm_storeu_pd(longest, _mm_max_pd(tw, _mm_max_pd(te, tu)));
    _mm_storeu_pd(area2, _mm_add_pd(area, area)); /* 2.0 * area, exactly */
    tally_shape(k, longest[0], area2[0]);
    tally_shape(k, longest[1], area2[1]);
}
#endif

gc_status gc_mesh_sums_compute(const gc_mesh *mesh, int64_t ar_stride,
                               double *ar_out, int64_t *n_ar, gc_mesh_sums *out, char *err)
{
    if (!mesh || !out || ar_stride < 1 || (ar_out && !n_ar)) {
        if (err) {
            snprintf(err, GC_ERROR_LEN, "gc_mesh_sums_compute: bad arguments");
        }
        return GC_ERR_ARGUMENT;
    }
    const double *v = mesh->vertices;
    const int64_t *f = mesh->faces;
    const int64_t nf = mesh->n_faces;
    /* reference point of the enclosed volume: the centre of all vertices' bounds */
    double vlo[3] = {INFINITY, INFINITY, INFINITY}, vhi[3] = {-INFINITY, -INFINITY, -INFINITY};
    for (int64_t i = 0; i < mesh->n_vertices; ++i) {
        for (int a = 0; a < 3; ++a) {
            vlo[a] = lesser(vlo[a], v[3 * i + a]);
            vhi[a] = greater(vhi[a], v[3 * i + a]);
        }
    }
    const double c[3] = {0.5 * (vlo[0] + vhi[0]), 0.5 * (vlo[1] + vhi[1]), 0.5 * (vlo[2] + vhi[2])};
    /* Accumulate in locals (the output could alias the vertices as far as the compiler knows). */
    sums_acc acc;
    sums_acc_init(&acc);
    shape_tally k = {ar_stride, 0, 0, 0, ar_out};
    int64_t t = 0;
#ifdef GC_STATS_SIMD
    sums_acc2 acc2;
    for (int a = 0; a < 3; ++a) {
        acc2.lo_b[a] = _mm_set1_pd(INFINITY);
        acc2.hi_b[a] = _mm_set1_pd(-INFINITY);
        acc2.e1[a] = acc2.e2[a] = acc2.per[a] = acc2.pair[a] = _mm_setzero_pd();
    }
    acc2.triple = acc2.area = acc2.vol6 = _mm_setzero_pd();
    for (; t + 1 < nf; t += 2) {
        if (bad_face(mesh, t) | bad_face(mesh, t + 1)) {
            report_bad_face(mesh, bad_face(mesh, t) ? t : t + 1, err);
            return GC_ERR_ARGUMENT;
        }
        PREFETCH_CORNERS(mesh, t + PREFETCH_AHEAD);
        PREFETCH_CORNERS(mesh, t + PREFETCH_AHEAD + 1);
        add_triangle_pair(&acc2, &k, v, f + 3 * t, c);
    }
    sums_acc2_fold(&acc2, &acc);
#endif
    for (; t < nf; ++t) {
        if (bad_face(mesh, t)) {
            report_bad_face(mesh, t, err);
            return GC_ERR_ARGUMENT;
        }
        PREFETCH_CORNERS(mesh, t + PREFETCH_AHEAD);
        double area2, longest = add_triangle(&acc, v + 3 * f[3 * t], v + 3 * f[3 * t + 1], v + 3 * f[3 * t + 2],
                                             c, &area2);
        tally_shape(&k, longest, area2);
    }
    for (int a = 0; a < 3; ++a) {
        out->box_lo[a] = acc.lo_b[a];
        out->box_hi[a] = acc.hi_b[a];
        out->e1[a] = acc.e1[a];
        out->e2[a] = acc.e2[a];
        out->perimeters[a] = acc.per[a];
        out->pair[a] = acc.pair[a];
    }
    out->triple = acc.triple;
    out->area = acc.area;
    out->vol6 = acc.vol6;
    out->n_good = k.n_good;
    if (n_ar) {
        *n_ar = k.n_sample;
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

/* Slots of the position table: a power of two, at least twice the vertices. */
static uint64_t table_slots(int64_t nv)
{
    uint64_t cap = 16;
    while (cap < 2u * (uint64_t)nv) {
        cap <<= 1;
    }
    return cap;
}

static uint64_t position_hash(const double *p)
{
    uint64_t h = splitmix(coord_bits(p[0]) + 0x9E3779B97F4A7C15ull);
    h = splitmix(h ^ coord_bits(p[1]));
    return splitmix(h ^ coord_bits(p[2]));
}

/* Hashes are computed this many vertices ahead, so the slot a vertex probes can be
 * fetched while earlier vertices are placed (the table is far bigger than a cache). */
#define HASH_AHEAD 16

/* id[i] = the first vertex at the same position as vertex i.  Open addressing in
 * table[cap] (zeroed); a slot holds the hash's high 32 bits above (index + 1), so
 * positions are compared (a vertex read elsewhere) only when those bits agree.
 * Returns the number of vertices merged into an earlier one. */
static int64_t merge_positions(const double *v, int64_t nv, uint64_t *table, uint64_t cap, uint32_t *id)
{
    uint64_t ring[HASH_AHEAD];
    for (int64_t i = 0; i < HASH_AHEAD && i < nv; ++i) {
        ring[i] = position_hash(v + 3 * i);
    }
    int64_t merged = 0;
    for (int64_t i = 0; i < nv; ++i) {
        const double *p = v + 3 * i;
        const uint64_t h = ring[i % HASH_AHEAD];
        if (i + HASH_AHEAD < nv) {
            const uint64_t later = position_hash(v + 3 * (i + HASH_AHEAD));
            ring[i % HASH_AHEAD] = later;
            GC_PREFETCH(table + (later & (cap - 1)));
        }
        const uint64_t tag = h & 0xFFFFFFFF00000000ull;
        for (uint64_t s = h & (cap - 1);; s = (s + 1) & (cap - 1)) {
            const uint64_t slot = table[s];
            if (slot == 0) {
                table[s] = tag | (uint64_t)(i + 1);
                id[i] = (uint32_t)i;
                break;
            }
            const uint32_t j = (uint32_t)slot - 1u;
            if ((slot & 0xFFFFFFFF00000000ull) == tag && same_position(v + 3 * (int64_t)j, p)) {
                id[i] = j;
                merged++;
                break;
            }
        }
    }
    return merged;
}

/* Merged vertex of a corner: id[x], or x itself when no position was merged. */
#define MERGED(id, x) ((id) ? (id)[x] : (uint32_t)(x))

/* The merged corners of face t, sorted: s[0] <= s[1] <= s[2]. */
#define FACE_CORNERS(f, id, t, s) \
    sort3(MERGED(id, (f)[3 * (t)]), MERGED(id, (f)[3 * (t) + 1]), MERGED(id, (f)[3 * (t) + 2]), s)

/* Sort three values into s[0] <= s[1] <= s[2] (branch-free min/max). */
static void sort3(uint32_t a, uint32_t b, uint32_t c, uint32_t s[3])
{
    uint32_t lo = a < b ? a : b, hi = a < b ? b : a;
    s[0] = lo < c ? lo : c;
    uint32_t m = lo < c ? c : lo; /* the larger of lo and c */
    s[1] = m < hi ? m : hi;
    s[2] = m < hi ? hi : m;
}

/* Every edge exactly twice?  The edges are grouped by their smaller merged endpoint
 * (a counting sort), and in each group every larger endpoint must occur twice.  A
 * face with corners s0 <= s1 <= s2 has edges (s0, s1), (s0, s2), (s1, s2).  id is
 * NULL when no positions merged (corners are their own ids); faces are checked
 * here, before any is used as an index.  end[nv + 1] and mark[nv] are zeroed
 * scratch, other[3 nf] scratch.  Returns 1, 0, or -1 with *bad the first bad face. */
static inline int edges_twice(const gc_mesh *mesh, const uint32_t *id, uint32_t *end, uint32_t *mark,
                              uint32_t *other, int64_t *bad)
{
    const int64_t *f = mesh->faces, nf = mesh->n_faces, nv = mesh->n_vertices;
    for (int64_t t = 0; t < nf; ++t) { /* end[lo + 1] = edges whose smaller endpoint is lo */
        if (bad_face(mesh, t)) {
            *bad = t;
            return -1;
        }
        uint32_t s[3];
        FACE_CORNERS(f, id, t, s);
        end[s[0] + 1] += 2;
        end[s[1] + 1] += 1;
    }
    for (int64_t i = 0; i < nv; ++i) { /* end[lo] = where lo's group begins */
        if (end[i + 1] % 2) {
            return 0; /* an odd number of edges from lo cannot pair up */
        }
        end[i + 1] += end[i];
    }
    for (int64_t t = 0; t < nf; ++t) { /* after the scatter, end[lo] is where lo's group ends */
        if (t + PREFETCH_AHEAD < nf) { /* where face t + PREFETCH_AHEAD will write, about */
            uint32_t p[3];
            FACE_CORNERS(f, id, t + PREFETCH_AHEAD, p);
            GC_PREFETCH_WRITE(other + end[p[0]]);
            GC_PREFETCH_WRITE(other + end[p[1]]);
        }
        uint32_t s[3];
        FACE_CORNERS(f, id, t, s);
        uint32_t *o = other + end[s[0]];
        o[0] = s[1];
        o[1] = s[2];
        end[s[0]] += 2;
        other[end[s[1]]++] = s[2];
    }
    uint32_t begin = 0;
    for (int64_t lo = 0; lo < nv; begin = end[lo], ++lo) {
        const uint32_t *o = other + begin;
        const uint32_t n = end[lo] - begin;
        if (n == 2) {
            if (o[0] != o[1]) {
                return 0;
            }
            continue;
        }
        for (uint32_t i = 0; i < n; ++i) { /* count each partner (mark[] near lo: cached) */
            mark[o[i]]++;
        }
        int ok = 1;
        for (uint32_t i = 0; i < n; ++i) {
            ok &= mark[o[i]] == 2;
        }
        for (uint32_t i = 0; i < n; ++i) {
            mark[o[i]] = 0;
        }
        if (!ok) {
            return 0;
        }
    }
    return 1;
}

gc_status gc_mesh_topology(const gc_mesh *mesh, int *watertight, int64_t *positions, char *err)
{
    if (!mesh || !watertight || !positions) {
        if (err) {
            snprintf(err, GC_ERROR_LEN, "gc_mesh_topology: bad arguments");
        }
        return GC_ERR_ARGUMENT;
    }
    *watertight = 0;
    *positions = 0;
    const int64_t nv = mesh->n_vertices, nf = mesh->n_faces;
    if (nv >= (int64_t)UINT32_MAX || nf > ((int64_t)UINT32_MAX - 1) / 3) {
        if (err) { /* 32-bit ids and offsets: 50 GB of mesh or more */
            snprintf(err, GC_ERROR_LEN, "mesh too large for the watertightness test: %lld vertices, %lld faces "
                     "(at most 2^32 - 2 vertices and (2^32 - 2) / 3 faces)", (long long)nv, (long long)nf);
        }
        return GC_ERR_ARGUMENT;
    }
    if (nf == 0) {
        *positions = nv; /* nothing merged: no vertex is compared */
        return GC_OK;
    }
    /* One buffer serves first as the position table, then as the grouped edges. */
    const uint64_t cap = table_slots(nv);
    const size_t buf_bytes = cap * sizeof(uint64_t) > (size_t)(3 * nf) * sizeof(uint32_t)
                                 ? cap * sizeof(uint64_t) : (size_t)(3 * nf) * sizeof(uint32_t);
    void *buf = calloc(buf_bytes, 1);
    uint32_t *id = malloc((size_t)nv * sizeof *id);      /* merged ids */
    uint32_t *end = calloc((size_t)nv + 1, sizeof *end); /* group offsets */
    uint32_t *mark = calloc((size_t)nv, sizeof *mark);   /* partner counts of one group */
    if (!buf || !id || !end || !mark) {
        if (err) {
            snprintf(err, GC_ERROR_LEN, "out of memory testing watertightness of %lld faces", (long long)nf);
        }
        free(buf), free(id), free(end), free(mark);
        return GC_ERR_NO_MEMORY;
    }
    const int64_t merged = merge_positions(mesh->vertices, nv, (uint64_t *)buf, cap, id);
    int64_t bad = -1;
    /* the buffer's table is spent: it now takes the grouped edges */
    const int wt = merged ? edges_twice(mesh, id, end, mark, (uint32_t *)buf, &bad)
                          : edges_twice(mesh, NULL, end, mark, (uint32_t *)buf, &bad);
    free(buf), free(id), free(end), free(mark);
    if (wt < 0) {
        report_bad_face(mesh, bad, err);
        return GC_ERR_ARGUMENT;
    }
    *watertight = wt;
    *positions = nv - merged;
    return GC_OK;
}

gc_status gc_mesh_watertight(const gc_mesh *mesh, int *watertight, char *err)
{
    int64_t positions;
    return gc_mesh_topology(mesh, watertight, &positions, err);
}
