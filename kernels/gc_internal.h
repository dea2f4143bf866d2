/* gc_internal.h - data layout shared by the kernels' translation units.
 *
 * Not part of the public interface.  A grid is flat arrays:
 *   nodes : one per (sub)grid, node 0 is the top level;
 *   cells : every node's cells, node k owning [first_cell, first_cell + nx*ny*nz);
 *   refs  : each reference's face index into the mesh (build only; freed after); a leaf
 *           cell owns references [begin, begin + count), in the Morton order of their
 *           triangles' centroids;
 *   ref_tris : the vertices of each reference's triangle and its face index, in packs
 *           of GC_LANES references (gc_pack) so that one coordinate of neighbouring
 *           references is one vector load;
 *   occ   : one bit per cell of every node, bit c % 64 of word c / 64 set when cell c holds
 *           references or a subgrid.  The walk reads a cell's bit, and its record only where
 *           the bit is set: an empty cell costs a bit of an array 64 times smaller than the
 *           records, which the caches keep where a big grid's records would not fit.
 * A cell whose count is GC_CELL_SUBGRID holds a subgrid: its begin is a node index.
 */
#ifndef GC_INTERNAL_H
#define GC_INTERNAL_H

#include "gridcal.h"

#include <math.h>
#include <stdint.h>

#if defined(__GNUC__)
#define GC_INLINE static inline __attribute__((always_inline))
#else
#define GC_INLINE static inline
#endif

/* A hint to start loading memory that will be needed soon; nothing where unsupported. */
#if defined(__GNUC__)
#define GC_PREFETCH(p) __builtin_prefetch(p)
#else
#define GC_PREFETCH(p) ((void)(p))
#endif

/* Minimum and maximum of finite values, inlined (fmin/fmax are library calls). */
#define GC_MIN(a, b) ((a) < (b) ? (a) : (b))
#define GC_MAX(a, b) ((a) > (b) ? (a) : (b))

typedef struct {
    double v0[3], v1[3], v2[3];
} gc_tri; /* 72 bytes */

/* The per-reference triangles are stored in packs of GC_LANES references:
 * coordinate c (3 * vertex + axis) of reference k is
 * ref_tris[k / GC_LANES].c[c][k % GC_LANES], and the mesh's face index of its
 * triangle is ref_tris[k / GC_LANES].id[k % GC_LANES].  The intersectors read
 * one triangle through a "lane view", a pointer to its coordinate 0, with the
 * coordinates GC_LANES doubles apart (GC_TV); the packed sign stage reads one
 * coordinate of a whole pack with one load (four lanes with AVX2, two halves of
 * two with SSE2).  The face index travels with the coordinates, so a hit needs
 * no lookup in another array.  76 bytes per reference; the last pack may have
 * unused lanes (zeros). */
#define GC_LANES 4
typedef struct {
    double c[9][GC_LANES];
    int32_t id[GC_LANES];
} gc_pack; /* 304 bytes */
#define GC_TV(t, c) ((t)[GC_LANES * (c)])
/* bytes of the per-reference triangles of n references */
#define GC_PACK_BYTES(n) ((((uint64_t)(n) + GC_LANES - 1) / GC_LANES) * (uint64_t)sizeof(gc_pack))

typedef struct {
    uint32_t begin; /* first reference, or the subgrid's node index */
    uint32_t count; /* number of references, or GC_CELL_SUBGRID */
} gc_cell;          /* 8 bytes */

#define GC_CELL_SUBGRID UINT32_MAX

typedef struct {
    double lo[3], hi[3];
    double cell[3];     /* cell size along each axis */
    double inv_cell[3]; /* 1 / cell */
    int32_t n[3];
    uint32_t first_cell;
    uint32_t depth;     /* 0 for the top level */
    uint32_t pad;
} gc_node;              /* 120 bytes */

_Static_assert(sizeof(gc_tri) == 72, "gc_tri is three packed vertices");
_Static_assert(sizeof(gc_pack) == 76 * GC_LANES, "gc_pack is GC_LANES triangles and their face indices");
_Static_assert(sizeof(gc_cell) == 8, "gc_cell is two 32-bit fields");
_Static_assert(sizeof(gc_node) == 120, "gc_node layout");

struct gc_grid {
    gc_pack *ref_tris;  /* a copy of each reference's triangle, parallel to refs, in packs
                         * (gc_pack): a cell's triangles stream from one contiguous block,
                         * so the cost of a test does not depend on where the triangle
                         * lies in memory */
    int64_t n_tris;
    gc_node *nodes;
    int64_t n_nodes;
    gc_cell *cells;
    int64_t n_cells;
    uint64_t *occ;      /* the cells' occupancy bits (above), GC_OCC_WORDS(n_cells) words, with
                         * occ_pad zero words before and after them */
    int64_t occ_pad;
    size_t ref_tris_mapped, cells_mapped, occ_mapped; /* bytes mapped by gc_big_alloc, 0 if malloc'd */
    uint32_t *refs;     /* the mesh face of each reference (build only; freed after) */
    int64_t n_refs;
    gc_intersector intersector;
    int mailbox;
    int levels;
};

/* Words of the occupancy bits of n cells. */
#define GC_OCC_WORDS(n) (((uint64_t)(n) + 63) / 64)

/* Whether cell idx (an index into the grid's cells) holds references or a subgrid.  idx may
 * lie up to one node's layer (nx * ny cells, the largest of any node) before the first cell or
 * past the last: the bits there are occ_pad zero words, so such a cell reads as empty.  The
 * shift of a negative idx is arithmetic (gcc and clang define it so): word floor(idx / 64). */
GC_INLINE uint32_t gc_occupied(const uint64_t *occ, int64_t idx)
{
    return (uint32_t)(occ[idx >> 6] >> ((uint64_t)idx & 63)) & 1u;
}

/* The one place a cell's index is computed. */
GC_INLINE uint64_t gc_cell_index(const gc_node *g, int32_t x, int32_t y, int32_t z)
{
    return (uint64_t)g->first_cell +
           (uint64_t)x + (uint64_t)g->n[0] * ((uint64_t)y + (uint64_t)g->n[1] * (uint64_t)z);
}

/* Direction components below this are flushed to +0: their reciprocal would
 * overflow, and over any representable t they move the ray by nothing. */
#define GC_DIRECTION_FLUSH 2.2250738585072014e-308 /* DBL_MIN */

/* A ray prepared once for every test it takes part in. */
typedef struct {
    double o[3], d[3];
    double inv_d[3];   /* 1/d, +-inf where d is +-0 */
    /* watertight test (Woop et al. 2013): axes and shear */
    int kx, ky, kz;
    double sx, sy, sz;
} gc_ray;

/* The watertight test's axes from the prepared direction r->d: kz the dominant axis,
 * kx and ky the others in the order that keeps the winding. */
GC_INLINE void gc_ray_axes(gc_ray *r)
{
    double ax = fabs(r->d[0]), ay = fabs(r->d[1]), az = fabs(r->d[2]);
    /* kz: the dominant axis (ties to the later one), by arithmetic, not
     * branches: for rays in every direction the comparisons are coin tosses. */
    const int x_max = (ax > ay) & (ax > az), y_max = !(ax > ay) & (ay > az);
    const int kz = 2 - 2 * x_max - y_max;
    static const int gc_next_axis[3] = {1, 2, 0};
    const int kx0 = gc_next_axis[kz], ky0 = gc_next_axis[kx0];
    /* keep the winding so the sign tests stay meaningful */
    const int flip = r->d[kz] < 0.0;
    const int swap = (kx0 ^ ky0) & -flip; /* exchanges kx and ky when flip, by arithmetic */
    r->kx = kx0 ^ swap;
    r->ky = ky0 ^ swap;
    r->kz = kz;
}

GC_INLINE void gc_ray_prepare(gc_ray *r, const double *o, const double *d)
{
    for (int i = 0; i < 3; ++i) {
        r->o[i] = o[i];
        /* -0.0 and +0.0 are the same direction: normalise so 1/d is +inf for both
         * and no sign of zero leaks into the traversal. */
        r->d[i] = (fabs(d[i]) < GC_DIRECTION_FLUSH) ? 0.0 : d[i];
        r->inv_d[i] = 1.0 / r->d[i];
    }
    gc_ray_axes(r);
    r->sx = r->d[r->kx] / r->d[r->kz];
    r->sy = r->d[r->ky] / r->d[r->kz];
    r->sz = 1.0 / r->d[r->kz];
}

/* The preparation on AVX2, for the AVX2 walk (traverse.c): the three components of the
 * direction flushed and inverted at once (lane i is component i's value, the fourth lane
 * zero), the two shear divisions as one; the same IEEE operations as gc_ray_prepare, so
 * the same ray, bit for bit.  sz is inv_d[kz]: both are 1.0 / d[kz]. */
#if defined(__GNUC__) && defined(__x86_64__) && defined(__SSE2__)
#include <immintrin.h>
#define GC_HAVE_AVX2_RAY 1
#define GC_AVX2_RAY __attribute__((target("avx2")))

/* x[0], x[1], x[2] and a zero: the fourth lane never holds whatever follows x in memory
 * (a subnormal there would slow every operation on the vector). */
GC_AVX2_RAY GC_INLINE __m256d gc_load3_avx2(const double *x)
{
    return _mm256_insertf128_pd(_mm256_castpd128_pd256(_mm_loadu_pd(x)), _mm_load_sd(x + 2), 1);
}

GC_AVX2_RAY GC_INLINE void gc_store3_avx2(double *x, __m256d v)
{
    _mm_storeu_pd(x, _mm256_castpd256_pd128(v));
    _mm_store_sd(x + 2, _mm256_extractf128_pd(v, 1));
}

/* |v| per lane: the sign bit cleared, as fabs does */
GC_AVX2_RAY GC_INLINE __m256d gc_fabs_avx2(__m256d v)
{
    return _mm256_andnot_pd(_mm256_castsi256_pd(_mm256_set1_epi64x(INT64_MIN)), v);
}

GC_AVX2_RAY GC_INLINE void gc_ray_prepare_avx2(gc_ray *r, const double *o, const double *d)
{
    const __m256d dv = gc_load3_avx2(d);
    const __m256d flush = _mm256_cmp_pd(gc_fabs_avx2(dv), _mm256_set1_pd(GC_DIRECTION_FLUSH), _CMP_LT_OQ);
    const __m256d df = _mm256_andnot_pd(flush, dv); /* +0.0 where flushed */
    gc_store3_avx2(r->o, gc_load3_avx2(o));
    gc_store3_avx2(r->d, df);
    gc_store3_avx2(r->inv_d, _mm256_div_pd(_mm256_set1_pd(1.0), df));
    gc_ray_axes(r);
    const __m128d s = _mm_div_pd(_mm_set_pd(r->d[r->ky], r->d[r->kx]), _mm_set1_pd(r->d[r->kz]));
    r->sx = _mm_cvtsd_f64(s);
    r->sy = _mm_cvtsd_f64(_mm_unpackhi_pd(s, s));
    r->sz = r->inv_d[r->kz];
}
#endif

/* Validate a mesh: positive counts, indices in range, finite vertices used by faces.
 * With lo and hi (both or neither may be NULL), the same pass returns the bounds
 * of the vertices that faces use (not widened; untouched for a mesh without faces). */
gc_status gc_check_mesh(const gc_mesh *mesh, int allow_empty, double lo[3], double hi[3], char *err);

/* The first part of gc_check_mesh: the counts and pointers (every face is left unread). */
gc_status gc_check_mesh_shape(const gc_mesh *mesh, int allow_empty, char *err);

/* Validate rays: finite origins, finite non-zero directions. */
gc_status gc_check_rays(int64_t n, const double *origins, const double *directions, char *err);

/* A grid's large traversal arrays (bigmem.c): from GC_HUGE_PAGE_BYTES on they are
 * mapped on their own and backed by huge pages where the OS offers them.
 * gc_big_alloc: zeroed memory, NULL when out of memory; *mapped is the length
 * mapped, or 0 for an ordinary calloc'd block.  gc_big_free releases either.
 * gc_big_move: the malloc'd block p of `bytes` moved into a mapping (p is
 * freed; *mapped its length), or p itself (*mapped = 0) when it is smaller or
 * the mapping fails.  A freed mapping of at most GC_BIG_KEEP_BYTES is kept for
 * a later gc_big_alloc of a half to all of its length (at most GC_BIG_KEEP
 * kept, the oldest unmapped first); gc_big_kept reports how many and how many
 * bytes, gc_release_memory (gridcal.h) unmaps them.  gc_big_alloc_raw with zero
 * = 0: the same, but a kept mapping comes back as its last user left it (for an
 * array its caller writes in full). */
#define GC_HUGE_PAGE_BYTES ((size_t)2 << 20)
#define GC_BIG_KEEP 4
#define GC_BIG_KEEP_BYTES ((size_t)256 << 20)
void *gc_big_alloc(size_t bytes, size_t *mapped);
void *gc_big_alloc_raw(size_t bytes, size_t *mapped, int zero);
void gc_big_free(void *p, size_t mapped);
void *gc_big_move(void *p, size_t bytes, size_t *mapped);
void gc_big_kept(int *count, size_t *bytes);

void gc_set_error(char *err, const char *fmt, ...)
#if defined(__GNUC__)
    __attribute__((format(printf, 2, 3)))
#endif
    ;

#endif /* GC_INTERNAL_H */
