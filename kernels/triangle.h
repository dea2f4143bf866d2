/* triangle.h - the two ray/triangle intersectors.
 *
 * Both return 1 and set *t_out when the ray meets the triangle at some
 * t in (0, t_max).  Neither uses an absolute epsilon: a scale-dependent
 * tolerance would break scenes scaled by 1e-20 or 1e20.  A degenerate
 * (zero-area) triangle is never hit (see GC_DET_ULPS).
 */
#ifndef GC_TRIANGLE_H
#define GC_TRIANGLE_H

#include "gc_internal.h"

/* Rounding-error bound on a determinant, in units of the magnitudes of the
 * products it sums (a few ulps: each product and sum rounds once).  A
 * determinant at or below it is rounding noise: the triangle is degenerate
 * (zero area) or the ray lies in its plane, and the test reports no hit
 * rather than a t made of noise.  Relative, so scenes scaled by 1e-20 or
 * 1e20 behave alike. */
#define GC_DET_ULPS (8.0 * 2.220446049250313e-16)

/* Moller and Trumbore, "Fast, minimum storage ray-triangle intersection",
 * JGT 2(1) 1997.  Not watertight: rays through shared edges or vertices can
 * slip between the two triangles when rounding disagrees. */
/* The rest of the Moller-Trumbore test for a candidate inside the triangle's
 * edges: depth, determinant bound and t.  Out of line, like the watertight
 * test's; the values it forms again come from the same operations. */
#if defined(__GNUC__)
__attribute__((noinline))
#endif
static int gc_isect_moller_trumbore_finish(const gc_ray *r, const double *tri, double sgn, double adet,
                                           double t_max, double *t_out)
{
    const double e1[3] = {GC_TV(tri, 3) - GC_TV(tri, 0), GC_TV(tri, 4) - GC_TV(tri, 1), GC_TV(tri, 5) - GC_TV(tri, 2)};
    const double e2[3] = {GC_TV(tri, 6) - GC_TV(tri, 0), GC_TV(tri, 7) - GC_TV(tri, 1), GC_TV(tri, 8) - GC_TV(tri, 2)};
    const double s[3] = {r->o[0] - GC_TV(tri, 0), r->o[1] - GC_TV(tri, 1), r->o[2] - GC_TV(tri, 2)};
    const double q[3] = {s[1] * e1[2] - s[2] * e1[1], s[2] * e1[0] - s[0] * e1[2],
                         s[0] * e1[1] - s[1] * e1[0]};
    const double tt = (e2[0] * q[0] + e2[1] * q[1] + e2[2] * q[2]) * sgn;
    if (!((tt > 0.0) & (tt < t_max * adet))) {
        return 0;
    }
    /* det = e1 . (d x e2): its rounding is bounded by the magnitudes of every product in it */
    const double mag = (fabs(e1[0]) + fabs(e1[1]) + fabs(e1[2])) *
                       (fabs(r->d[0]) + fabs(r->d[1]) + fabs(r->d[2])) *
                       (fabs(e2[0]) + fabs(e2[1]) + fabs(e2[2]));
    if (!(adet > GC_DET_ULPS * mag)) {
        return 0;
    }
    const double t = tt / adet;
    if (!(t > 0.0 && t < t_max)) { /* the scaled comparison can round the other way */
        return 0;
    }
    *t_out = t;
    return 1;
}

GC_INLINE int gc_isect_moller_trumbore(const gc_ray *r, const double *tri, double t_max,
                                       double *t_out)
{
    const double e1[3] = {GC_TV(tri, 3) - GC_TV(tri, 0), GC_TV(tri, 4) - GC_TV(tri, 1), GC_TV(tri, 5) - GC_TV(tri, 2)};
    const double e2[3] = {GC_TV(tri, 6) - GC_TV(tri, 0), GC_TV(tri, 7) - GC_TV(tri, 1), GC_TV(tri, 8) - GC_TV(tri, 2)};
    const double p[3] = {r->d[1] * e2[2] - r->d[2] * e2[1], r->d[2] * e2[0] - r->d[0] * e2[2],
                         r->d[0] * e2[1] - r->d[1] * e2[0]};
    const double det = e1[0] * p[0] + e1[1] * p[1] + e1[2] * p[2];
    const double s[3] = {r->o[0] - GC_TV(tri, 0), r->o[1] - GC_TV(tri, 1), r->o[2] - GC_TV(tri, 2)};
    /* Barycentrics and t scaled by det, compared with det's sign folded in, so
     * nothing divides before a hit.  The cheap range tests come first and reject
     * most candidates; depth and the determinant's rounding bound, which needs
     * every magnitude, are formed only for a candidate that passed them
     * (gc_isect_moller_trumbore_finish).  The verdict is the same conjunction
     * in any order. */
    const double sgn = det < 0.0 ? -1.0 : 1.0;
    const double adet = det * sgn;
    const double u = (s[0] * p[0] + s[1] * p[1] + s[2] * p[2]) * sgn;
    if (!((u >= 0.0) & (u <= adet))) {
        return 0;
    }
    const double q[3] = {s[1] * e1[2] - s[2] * e1[1], s[2] * e1[0] - s[0] * e1[2],
                         s[0] * e1[1] - s[1] * e1[0]};
    const double v = (r->d[0] * q[0] + r->d[1] * q[1] + r->d[2] * q[2]) * sgn;
    if (!((v >= 0.0) & (u + v <= adet))) {
        return 0;
    }
    return gc_isect_moller_trumbore_finish(r, tri, sgn, adet, t_max, t_out);
}

/* Woop, Benthin and Wald, "Watertight Ray/Triangle Intersection", JCGT 2(1)
 * 2013.  Vertices are translated to the ray origin and sheared so the ray runs
 * along +z; the 2D edge functions U, V, W of a shared edge are then computed
 * from identical operands in both triangles and are exact negations of each
 * other, so no ray slips through an edge or a vertex.  In double precision the
 * paper's fallback for an exactly zero edge function is not needed: zero is
 * handled consistently by the inclusive sign test.  Requires -ffp-contract=off
 * (a fused multiply-add would break the negation symmetry). */
/* The rest of the watertight test, for a ray whose line passes through the
 * triangle (same sign of U, V, W): depth, determinant bound and t.  Kept out of
 * line so the common rejection stays short; the sheared coordinates and the
 * edge functions are formed again by the same operations, so they are the same
 * values (and the caller need not hand them over). */
GC_INLINE int gc_isect_watertight_finish_inline(const gc_ray *r, const double *tri, double t_max, double *t_out)
{
    const int kx = r->kx, ky = r->ky, kz = r->kz;
    const double sx = r->sx, sy = r->sy;
    const double a_x = GC_TV(tri, kx) - r->o[kx], a_y = GC_TV(tri, ky) - r->o[ky], a_z = GC_TV(tri, kz) - r->o[kz];
    const double b_x = GC_TV(tri, 3 + kx) - r->o[kx], b_y = GC_TV(tri, 3 + ky) - r->o[ky],
                 b_z = GC_TV(tri, 3 + kz) - r->o[kz];
    const double c_x = GC_TV(tri, 6 + kx) - r->o[kx], c_y = GC_TV(tri, 6 + ky) - r->o[ky],
                 c_z = GC_TV(tri, 6 + kz) - r->o[kz];
    const double ax = a_x - sx * a_z, ay = a_y - sy * a_z;
    const double bx = b_x - sx * b_z, by = b_y - sy * b_z;
    const double cx = c_x - sx * c_z, cy = c_y - sy * c_z;
    const double u = cx * by - cy * bx;
    const double v = ax * cy - ay * cx;
    const double w = bx * ay - by * ax;
    const double det = u + v + w;
    const double az = r->sz * a_z, bz = r->sz * b_z, cz = r->sz * c_z;
    const double tt = u * az + v * bz + w * cz;
    /* det's sign folded into T, so that nothing divides before a hit */
    const double sgn = det < 0.0 ? -1.0 : 1.0;
    const double adet = det * sgn;
    const double ts = tt * sgn;
    if (!((ts > 0.0) & (ts < t_max * adet))) {
        return 0;
    }
    /* Rounding bound of det.  Each sheared coordinate (e.g. ax = a[kx] - sx a[kz])
     * carries an error of about one ulp of the magnitudes it was made from
     * (max_ = |a[kx]| + |sx a[kz]|), which can exceed what is left of it after
     * cancellation; a product p q then errs by about m_p |q| + |p| m_q. */
    const double max_ = fabs(a_x) + fabs(sx * a_z), may = fabs(a_y) + fabs(sy * a_z);
    const double mbx = fabs(b_x) + fabs(sx * b_z), mby = fabs(b_y) + fabs(sy * b_z);
    const double mcx = fabs(c_x) + fabs(sx * c_z), mcy = fabs(c_y) + fabs(sy * c_z);
    const double mag = mcx * fabs(by) + fabs(cx) * mby + mcy * fabs(bx) + fabs(cy) * mbx + max_ * fabs(cy) +
                       fabs(ax) * mcy + may * fabs(cx) + fabs(ay) * mcx + mbx * fabs(ay) + fabs(bx) * may +
                       mby * fabs(ax) + fabs(by) * max_;
    if (!(adet > GC_DET_ULPS * mag)) {
        return 0;
    }
    const double t = ts / adet;
    if (!(t > 0.0 && t < t_max)) {
        return 0;
    }
    *t_out = t;
    return 1;
}

#if defined(__GNUC__)
__attribute__((noinline))
#endif
static int gc_isect_watertight_finish(const gc_ray *r, const double *tri, double t_max, double *t_out)
{
    return gc_isect_watertight_finish_inline(r, tri, t_max, t_out);
}

GC_INLINE int gc_isect_watertight(const gc_ray *r, const double *tri, double t_max, double *t_out)
{
    const int kx = r->kx, ky = r->ky, kz = r->kz;
    const double sx = r->sx, sy = r->sy;
    /* indexed loads: the permuted coordinates straight from the triangle */
    const double a_z = GC_TV(tri, kz) - r->o[kz], b_z = GC_TV(tri, 3 + kz) - r->o[kz],
                 c_z = GC_TV(tri, 6 + kz) - r->o[kz];
    const double ax = (GC_TV(tri, kx) - r->o[kx]) - sx * a_z, ay = (GC_TV(tri, ky) - r->o[ky]) - sy * a_z;
    const double bx = (GC_TV(tri, 3 + kx) - r->o[kx]) - sx * b_z, by = (GC_TV(tri, 3 + ky) - r->o[ky]) - sy * b_z;
    const double cx = (GC_TV(tri, 6 + kx) - r->o[kx]) - sx * c_z, cy = (GC_TV(tri, 6 + ky) - r->o[ky]) - sy * c_z;
    const double u = cx * by - cy * bx;
    const double v = ax * cy - ay * cx;
    const double w = bx * ay - by * ax;
    /* The paper's sign tests first: they reject most candidates, and what
     * follows (gc_isect_watertight_finish) runs only for a ray that passes
     * them.  The verdict is the same conjunction in any order. */
    const int inside = ((u >= 0.0) & (v >= 0.0) & (w >= 0.0)) | ((u <= 0.0) & (v <= 0.0) & (w <= 0.0));
    if (!inside) {
        return 0;
    }
    return gc_isect_watertight_finish(r, tri, t_max, t_out);
}

#if defined(__SSE2__)
#include <emmintrin.h>
#define GC_HAVE_PACKED_WATERTIGHT 1

/* The ray as the two-lane sign stage uses it: the permuted origin and the
 * shear broadcast to both lanes, formed once a ray (the trace, traverse_impl.h). */
typedef struct {
    __m128d ox, oy, oz, sx, sy;
    int64_t kx, ky, kz; /* the permuted axes, in doubles within a pack's coordinate row */
} gc_ray2;

GC_INLINE void gc_ray2_prepare(gc_ray2 *q, const gc_ray *r)
{
    q->kx = GC_LANES * r->kx;
    q->ky = GC_LANES * r->ky;
    q->kz = GC_LANES * r->kz;
    q->ox = _mm_set1_pd(r->o[r->kx]);
    q->oy = _mm_set1_pd(r->o[r->ky]);
    q->oz = _mm_set1_pd(r->o[r->kz]);
    q->sx = _mm_set1_pd(r->sx);
    q->sy = _mm_set1_pd(r->sy);
}

/* The rejection stage of gc_isect_watertight for two neighbouring lanes of a
 * pack at once (c points at the first lane's coordinate 0): lane l of every
 * vector is exactly the scalar test's value for that lane's triangle (the same
 * IEEE operations in the same order; no contraction).  Returns bit l set when
 * lane l's ray line passes through its triangle; gc_isect_watertight_finish
 * decides the rest for that lane. */
GC_INLINE int gc_isect_watertight_signs2(const gc_ray2 *q, const double *c)
{
    const double *px = c + q->kx, *py = c + q->ky, *pz = c + q->kz;
    const __m128d a_z = _mm_sub_pd(_mm_loadu_pd(pz), q->oz);
    const __m128d b_z = _mm_sub_pd(_mm_loadu_pd(pz + 3 * GC_LANES), q->oz);
    const __m128d c_z = _mm_sub_pd(_mm_loadu_pd(pz + 6 * GC_LANES), q->oz);
    const __m128d ax = _mm_sub_pd(_mm_sub_pd(_mm_loadu_pd(px), q->ox), _mm_mul_pd(q->sx, a_z));
    const __m128d ay = _mm_sub_pd(_mm_sub_pd(_mm_loadu_pd(py), q->oy), _mm_mul_pd(q->sy, a_z));
    const __m128d bx = _mm_sub_pd(_mm_sub_pd(_mm_loadu_pd(px + 3 * GC_LANES), q->ox), _mm_mul_pd(q->sx, b_z));
    const __m128d by = _mm_sub_pd(_mm_sub_pd(_mm_loadu_pd(py + 3 * GC_LANES), q->oy), _mm_mul_pd(q->sy, b_z));
    const __m128d cx = _mm_sub_pd(_mm_sub_pd(_mm_loadu_pd(px + 6 * GC_LANES), q->ox), _mm_mul_pd(q->sx, c_z));
    const __m128d cy = _mm_sub_pd(_mm_sub_pd(_mm_loadu_pd(py + 6 * GC_LANES), q->oy), _mm_mul_pd(q->sy, c_z));
    const __m128d u = _mm_sub_pd(_mm_mul_pd(cx, by), _mm_mul_pd(cy, bx));
    const __m128d v = _mm_sub_pd(_mm_mul_pd(ax, cy), _mm_mul_pd(ay, cx));
    const __m128d w = _mm_sub_pd(_mm_mul_pd(bx, ay), _mm_mul_pd(by, ax));
    const __m128d zero = _mm_setzero_pd();
    const __m128d ge = _mm_and_pd(_mm_and_pd(_mm_cmpge_pd(u, zero), _mm_cmpge_pd(v, zero)), _mm_cmpge_pd(w, zero));
    const __m128d le = _mm_and_pd(_mm_and_pd(_mm_cmple_pd(u, zero), _mm_cmple_pd(v, zero)), _mm_cmple_pd(w, zero));
    return _mm_movemask_pd(_mm_or_pd(ge, le));
}

/* The rejection stage for a whole pack (c = &pack->c[0][0]): its GC_LANES
 * lanes two at a time.  Bit l of the result is lane l's verdict. */
GC_INLINE int gc_isect_watertight_signs_sse2(const gc_ray2 *q, const double *c)
{
    int m = 0;
    for (int l = 0; l < GC_LANES; l += 2) {
        m |= gc_isect_watertight_signs2(q, c + l) << l;
    }
    return m;
}

/* AVX2: the same stage over four lanes at once.  Compiled for AVX2 whatever
 * the build's flags (a function attribute) and called only after the host was
 * found to have it (traverse.c); same operations per lane, so the same bits. */
#if defined(__GNUC__) && (defined(__x86_64__) || defined(__i386__))
#include <immintrin.h>
#define GC_HAVE_AVX2_WATERTIGHT 1
#define GC_AVX2 __attribute__((target("avx2")))
_Static_assert(GC_LANES == 4, "the AVX2 sign stage reads four lanes at once");

typedef struct {
    __m256d ox, oy, oz, sx, sy;
    int64_t kx, ky, kz;
} gc_ray4;

GC_AVX2 GC_INLINE void gc_ray4_prepare(gc_ray4 *q, const gc_ray *r)
{
    q->kx = GC_LANES * r->kx;
    q->ky = GC_LANES * r->ky;
    q->kz = GC_LANES * r->kz;
    q->ox = _mm256_set1_pd(r->o[r->kx]);
    q->oy = _mm256_set1_pd(r->o[r->ky]);
    q->oz = _mm256_set1_pd(r->o[r->kz]);
    q->sx = _mm256_set1_pd(r->sx);
    q->sy = _mm256_set1_pd(r->sy);
}

GC_AVX2 GC_INLINE int gc_isect_watertight_signs_avx2(const gc_ray4 *q, const double *c)
{
    const double *px = c + q->kx, *py = c + q->ky, *pz = c + q->kz;
    const __m256d a_z = _mm256_sub_pd(_mm256_loadu_pd(pz), q->oz);
    const __m256d b_z = _mm256_sub_pd(_mm256_loadu_pd(pz + 3 * GC_LANES), q->oz);
    const __m256d c_z = _mm256_sub_pd(_mm256_loadu_pd(pz + 6 * GC_LANES), q->oz);
    const __m256d ax = _mm256_sub_pd(_mm256_sub_pd(_mm256_loadu_pd(px), q->ox), _mm256_mul_pd(q->sx, a_z));
    const __m256d ay = _mm256_sub_pd(_mm256_sub_pd(_mm256_loadu_pd(py), q->oy), _mm256_mul_pd(q->sy, a_z));
    const __m256d bx =
        _mm256_sub_pd(_mm256_sub_pd(_mm256_loadu_pd(px + 3 * GC_LANES), q->ox), _mm256_mul_pd(q->sx, b_z));
    const __m256d by =
        _mm256_sub_pd(_mm256_sub_pd(_mm256_loadu_pd(py + 3 * GC_LANES), q->oy), _mm256_mul_pd(q->sy, b_z));
    const __m256d cx =
        _mm256_sub_pd(_mm256_sub_pd(_mm256_loadu_pd(px + 6 * GC_LANES), q->ox), _mm256_mul_pd(q->sx, c_z));
    const __m256d cy =
        _mm256_sub_pd(_mm256_sub_pd(_mm256_loadu_pd(py + 6 * GC_LANES), q->oy), _mm256_mul_pd(q->sy, c_z));
    const __m256d u = _mm256_sub_pd(_mm256_mul_pd(cx, by), _mm256_mul_pd(cy, bx));
    const __m256d v = _mm256_sub_pd(_mm256_mul_pd(ax, cy), _mm256_mul_pd(ay, cx));
    const __m256d w = _mm256_sub_pd(_mm256_mul_pd(bx, ay), _mm256_mul_pd(by, ax));
    const __m256d zero = _mm256_setzero_pd();
    const __m256d ge = _mm256_and_pd(_mm256_and_pd(_mm256_cmp_pd(u, zero, _CMP_GE_OQ), _mm256_cmp_pd(v, zero, _CMP_GE_OQ)),
                                     _mm256_cmp_pd(w, zero, _CMP_GE_OQ));
    const __m256d le = _mm256_and_pd(_mm256_and_pd(_mm256_cmp_pd(u, zero, _CMP_LE_OQ), _mm256_cmp_pd(v, zero, _CMP_LE_OQ)),
                                     _mm256_cmp_pd(w, zero, _CMP_LE_OQ));
    return _mm256_movemask_pd(_mm256_or_pd(ge, le));
}
#endif
#endif

#endif /* GC_TRIANGLE_H */
