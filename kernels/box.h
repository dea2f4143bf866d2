/* box.h - ray/box slab test.
 *
 * Robust to direction components of +0 and -0 (the ray lies in the slab or
 * misses it; 0 * inf never forms) and to origins inside or on the box.  Every
 * comparison is written so that a NaN makes it fail.
 */
#ifndef GC_BOX_H
#define GC_BOX_H

#include "gc_internal.h"

/* Each slab's [t_near, t_far] is widened by this many ulps of its values, so
 * a ray that grazes the box along an edge or through a corner, where rounding
 * can make one slab's exit fall a hair before another's entry, still enters
 * (pbrt widens t_far by 1 + 2 gamma(3) for the same reason). */
#define GC_SLAB_WIDEN (4.0 * 2.220446049250313e-16)

/* Clip the ray's interval [*t0, *t1] to the box [lo, hi].  Returns 1 if a
 * non-empty interval remains (a ray touching the box in one point counts).
 * A ray parallel to a slab counts as inside it within a few ulps of the
 * slab's planes, for the same reason. */
GC_INLINE int gc_ray_box_clip(const gc_ray *r, const double lo[3], const double hi[3],
                              double *t0, double *t1)
{
    double ta = *t0, tb = *t1;
    for (int i = 0; i < 3; ++i) {
        if (r->d[i] == 0.0) {
            /* parallel to the slab: inside it for every t, or never */
            const double pad = GC_SLAB_WIDEN * fmax(fabs(lo[i]), fabs(hi[i]));
            if (!(r->o[i] >= lo[i] - pad && r->o[i] <= hi[i] + pad)) {
                return 0;
            }
            continue;
        }
        double tn = (lo[i] - r->o[i]) * r->inv_d[i];
        double tf = (hi[i] - r->o[i]) * r->inv_d[i];
        /* minima and maxima, not branches: which slab plane comes first is a
         * coin toss for the branch predictor when rays go every way */
        const double t_lo = tn > tf ? tf : tn, t_hi = tn > tf ? tn : tf;
        const double wn = t_lo - GC_SLAB_WIDEN * fabs(t_lo);
        const double wf = t_hi + GC_SLAB_WIDEN * fabs(t_hi);
        ta = wn > ta ? wn : ta;
        tb = wf < tb ? wf : tb;
    }
    if (!(ta <= tb)) {
        return 0;
    }
    *t0 = ta;
    *t1 = tb;
    return 1;
}

/* The same clip on AVX2, the three slabs at once, for the AVX2 walk (traverse.c).  Lane
 * i of each vector is slab i's value, lane 3 is zero (gc_load3_avx2) and takes no part;
 * every lane's arithmetic is gc_ray_box_clip's, a slab the ray is parallel to enters as
 * [-inf, inf] where the loop above skips it, and the slabs' ends are folded into the
 * interval in the loop's order by the same maxsd and minsd (so a NaN end is ignored as
 * the loop's comparisons ignore it): the same interval, bit for bit. */
#if defined(GC_HAVE_AVX2_RAY)
GC_AVX2_RAY GC_INLINE int gc_ray_box_clip_avx2(const gc_ray *r, const double lo[3], const double hi[3],
                                               double *t0, double *t1)
{
    const __m256d o = gc_load3_avx2(r->o), d = gc_load3_avx2(r->d), inv_d = gc_load3_avx2(r->inv_d);
    const __m256d l = gc_load3_avx2(lo), h = gc_load3_avx2(hi);
    const __m256d zero = _mm256_setzero_pd(), w = _mm256_set1_pd(GC_SLAB_WIDEN);
    const __m256d moves = _mm256_cmp_pd(d, zero, _CMP_NEQ_UQ);
    /* parallel to a slab: inside it within the pad, or no interval */
    const __m256d pad = _mm256_mul_pd(w, _mm256_max_pd(gc_fabs_avx2(l), gc_fabs_avx2(h)));
    const __m256d inside = _mm256_and_pd(_mm256_cmp_pd(o, _mm256_sub_pd(l, pad), _CMP_GE_OQ),
                                         _mm256_cmp_pd(o, _mm256_add_pd(h, pad), _CMP_LE_OQ));
    if (_mm256_movemask_pd(_mm256_or_pd(moves, inside)) != 0xf) {
        return 0;
    }
    const __m256d tn = _mm256_mul_pd(_mm256_sub_pd(l, o), inv_d);
    const __m256d tf = _mm256_mul_pd(_mm256_sub_pd(h, o), inv_d);
    const __m256d swap = _mm256_cmp_pd(tn, tf, _CMP_GT_OQ);
    const __m256d t_lo = _mm256_blendv_pd(tn, tf, swap), t_hi = _mm256_blendv_pd(tf, tn, swap);
    __m256d wn = _mm256_sub_pd(t_lo, _mm256_mul_pd(w, gc_fabs_avx2(t_lo)));
    __m256d wf = _mm256_add_pd(t_hi, _mm256_mul_pd(w, gc_fabs_avx2(t_hi)));
    wn = _mm256_blendv_pd(_mm256_set1_pd(-INFINITY), wn, moves);
    wf = _mm256_blendv_pd(_mm256_set1_pd(INFINITY), wf, moves);
    const __m128d wn01 = _mm256_castpd256_pd128(wn), wf01 = _mm256_castpd256_pd128(wf);
    __m128d ta = _mm_max_sd(wn01, _mm_set_sd(*t0));
    __m128d tb = _mm_min_sd(wf01, _mm_set_sd(*t1));
    ta = _mm_max_sd(_mm_unpackhi_pd(wn01, wn01), ta);
    tb = _mm_min_sd(_mm_unpackhi_pd(wf01, wf01), tb);
    ta = _mm_max_sd(_mm256_extractf128_pd(wn, 1), ta);
    tb = _mm_min_sd(_mm256_extractf128_pd(wf, 1), tb);
    const double a = _mm_cvtsd_f64(ta), b = _mm_cvtsd_f64(tb);
    if (!(a <= b)) {
        return 0;
    }
    *t0 = a;
    *t1 = b;
    return 1;
}
#endif

#endif /* GC_BOX_H */
