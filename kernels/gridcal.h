/* gridcal.h - the public interface of gridcal's grid ray-tracing kernels.
 *
 * C99, no Python.  Everything exported starts with gc_ / GC_.
 *
 * A grid is built once from a triangle mesh and then traversed by batches of
 * rays.  Geometry is double precision throughout: scenes scaled by 1e-20 or
 * 1e20 stay representable (products of two coordinates reach 1e40, which
 * single precision cannot hold).
 *
 * Grids are uniform (one level) or nested (a cell holding more than a
 * threshold of references gets a subgrid over that cell, recursively, up to
 * GC_MAX_LEVELS).  Cells are offsets into one flat reference array built by
 * counting sort; no pointers appear in traversal data.
 *
 * Traversal is first-hit 3D-DDA (Amanatides and Woo 1987) with optional
 * mailboxing and early exit once the nearest hit lies inside the current
 * cell.  It exists as two twins compiled from one source (traverse_impl.h):
 * the timed twin counts nothing; the instrumented twin counts, per ray, the
 * cells visited, the triangle tests and the subgrids entered.
 *
 * Every function that can fail returns a gc_status and, where it takes an
 * error buffer, writes a one-line message naming the problem into it.
 */
#ifndef GRIDCAL_H
#define GRIDCAL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define GC_VERSION_STRING "0.1.0"

/* Deepest nesting a grid may have (top level counts as level 1). */
#define GC_MAX_LEVELS 8
/* Largest number of cells over all levels of one grid: cell offsets are 32-bit. */
#define GC_MAX_CELLS ((uint64_t)UINT32_MAX - 1u)
/* Largest number of triangle references over all cells of one grid. */
#define GC_MAX_REFS ((uint64_t)UINT32_MAX - 1u)
/* Most threads a build uses (gc_build_params.threads above it uses this many). */
#define GC_MAX_THREADS 64
/* Default limit on the memory one grid may take (bytes); 0 in gc_build_params selects it. */
#define GC_DEFAULT_MEMORY_LIMIT_BYTES ((uint64_t)8u << 30)
/* Length of the error buffers the API fills. */
#define GC_ERROR_LEN 256

typedef enum {
    GC_OK = 0,
    GC_ERR_ARGUMENT = 1,   /* an input is malformed (index out of range, NaN, bad resolution) */
    GC_ERR_OVERFLOW = 2,   /* a cell or reference count does not fit the grid's 32-bit offsets */
    GC_ERR_MEMORY_LIMIT = 3, /* the grid would exceed the caller's memory limit */
    GC_ERR_NO_MEMORY = 4   /* malloc failed */
} gc_status;

typedef enum {
    GC_MOLLER_TRUMBORE = 0, /* Moller and Trumbore 1997, without an epsilon on the determinant */
    GC_WATERTIGHT = 1       /* Woop, Benthin and Wald, JCGT 2(1) 2013 */
} gc_intersector;

typedef enum {
    GC_INSERT_EXACT = 0,  /* triangle/box overlap by the separating axis test (Akenine-Moller 2001) */
    GC_INSERT_BOUNDS = 1  /* every cell the triangle's bounding box overlaps */
} gc_insertion;

/* A triangle mesh: vertices (n_vertices, 3) row-major, faces (n_faces, 3) row-major. */
typedef struct {
    const double *vertices;
    int64_t n_vertices;
    const int64_t *faces;
    int64_t n_faces;
} gc_mesh;

/* How to build a grid.  Start from gc_build_params_default(). */
typedef struct {
    int32_t resolution[3];      /* top level cells along x, y, z; each >= 1 */
    gc_intersector intersector;
    gc_insertion insertion;
    int mailbox;                /* nonzero: test each triangle at most once per ray */
    int has_box;                /* nonzero: use box_lo/box_hi instead of the mesh's box */
    double box_lo[3], box_hi[3];
    uint64_t memory_limit_bytes; /* 0: GC_DEFAULT_MEMORY_LIMIT_BYTES */

    /* Nesting.  levels = 1 builds a uniform grid. */
    int levels;
    /* A cell with more references than this gets a subgrid (rule-based levels). */
    uint32_t subdivide_threshold;
    /* Per-level rule for subgrids at depth d (1 <= d < levels): a subgrid over n
     * references gets total cells (level_scale[d] * n)^level_exponent[d], split into
     * near-cubic cells along its box (n_i = d_i * cbrt(M / (d_x d_y d_z)), each >= 1).
     * Manta's RecursiveGrid: scale 8 and exponent 3 / (2L + 1 - 2d). */
    double level_scale[GC_MAX_LEVELS];
    double level_exponent[GC_MAX_LEVELS];
    /* Optional explicit resolutions of the depth-1 subgrids: (nx*ny*nz of the top
     * level, 3) row-major, indexed like the top level's cells; a row of zeros means
     * no subgrid for that cell.  Overrides the rule and the threshold at depth 1;
     * deeper levels follow subgrid_resolutions2 or the rule.  NULL: use the rule. */
    const int32_t *subgrid_resolutions;
    /* Optional explicit resolutions of the depth-2 subgrids (needs
     * subgrid_resolutions and levels >= 3): one row for every cell of every depth-1
     * subgrid, the subgrids in the order of their top-level cells and each one's
     * cells x fastest -- the rows of top cell c's subgrid start at the sum of
     * nx*ny*nz over the non-zero rows of subgrid_resolutions before c.  A row of
     * zeros means no subgrid.  Overrides the rule and the threshold at depth 2;
     * deeper levels follow the rule.  NULL: use the rule. */
    const int32_t *subgrid_resolutions2;
    /* Rows of subgrid_resolutions2 (checked against the depth-1 subgrids' cells). */
    int64_t n_subgrid_resolutions2;
    /* Largest per-axis resolution the rule may produce for a subgrid. */
    int32_t rule_max_axis;
    /* Threads the build may use (0 or 1: the calling thread only; at most
     * GC_MAX_THREADS).  The passes over the triangles and the references are split
     * into this many parts; the grid is the same, byte for byte, for any number. */
    int threads;
} gc_build_params;

typedef struct gc_grid gc_grid;

/* What a built grid holds. */
typedef struct {
    int64_t n_triangles;
    int64_t n_nodes;        /* grids: 1 for the top level plus one per subgrid */
    int64_t n_cells;        /* cells over all levels */
    int64_t n_refs;         /* triangle references over all leaf cells */
    int64_t n_empty_cells;  /* leaf cells with no reference */
    int64_t memory_bytes;   /* bytes held by the grid */
    int32_t levels;         /* deepest level actually built */
    int32_t resolution[3];  /* top level */
    double box_lo[3], box_hi[3];
    gc_intersector intersector;
    int mailbox;
} gc_grid_info;

/* The defaults: 1x1x1, watertight, exact insertion, no mailbox, one level,
 * threshold 2, Manta's rule for deeper levels. */
gc_build_params gc_build_params_default(void);

/* The grid box rule: the mesh's bounding box with every degenerate axis
 * widened (see gc_grid_box in grid.c).  lo/hi receive the box. */
gc_status gc_mesh_box(const gc_mesh *mesh, double lo[3], double hi[3], char *err);
void gc_widen_box(double lo[3], double hi[3]);

/* Build a grid.  On success *out owns the grid (free with gc_grid_free).  On
 * failure *out is NULL, err holds a one-line message and nothing leaks.  A mesh
 * with no faces is accepted only with an explicit box (an empty grid, used to
 * time stepping alone). */
gc_status gc_grid_build(const gc_mesh *mesh, const gc_build_params *params,
                        gc_grid **out, char *err);
void gc_grid_free(gc_grid *grid);
/* gc_grid_free keeps a freed grid's largest arrays (up to 256 MiB in all) for the
 * next build to reuse, sparing it the kernel's zeroing of fresh pages; this gives
 * them back to the OS.  Safe to call at any time, from any thread. */
void gc_release_memory(void);
void gc_grid_get_info(const gc_grid *grid, gc_grid_info *info);

/* Per-cell reference counts of the top level, (nx*ny*nz) values; a cell with a
 * subgrid reports the references of its whole subtree. */
void gc_grid_top_counts(const gc_grid *grid, int64_t *counts);

/* First hit for n rays, origins and directions (n, 3) row-major.  Directions
 * need not be unit length; t is in units of the given direction.  Hits count
 * for t > 0.  A miss gives t = +inf and prim = -1.  Timed twin: counts nothing. */
gc_status gc_intersect(const gc_grid *grid, int64_t n, const double *origins,
                       const double *directions, double *t, int32_t *prim, char *err);

/* The instrumented twin: same hits, plus per ray the cells visited (all levels),
 * the triangle tests performed, the subgrids entered, the occupied cells
 * entered (the cells holding triangles that the walk tested, at every level; a
 * cell holding a subgrid is not one of them, its own cells are) and the
 * occupancy changes: the cells of a walk (top grid or subgrid) that are empty
 * after a non-empty one or non-empty after an empty one, the cell before a
 * walk's first counting as non-empty (a cell holding a subgrid is non-empty).
 * Where a walk passes from empty cells to occupied ones the branch that decides
 * whether a cell is tested goes the other way (docs/calibration.md, "One T_step
 * for every scene").  Any of the count arrays may be NULL. */
gc_status gc_count(const gc_grid *grid, int64_t n, const double *origins,
                   const double *directions, double *t, int32_t *prim,
                   uint32_t *steps, uint32_t *tests, uint32_t *subgrids, uint32_t *visits,
                   uint32_t *changes, char *err);

/* Timed batch: trace the n rays `loops` times with the timed twin and return the
 * elapsed wall time (CLOCK_MONOTONIC, ns) around all loops and a checksum of every
 * result, so that no work can be optimised away. */
gc_status gc_bench_intersect(const gc_grid *grid, int64_t n, const double *origins,
                             const double *directions, int64_t loops,
                             int64_t *elapsed_ns, double *checksum, char *err);

/* The instruction set of the timed watertight twin's sign stage: "avx2" (four
 * triangles at once, chosen when the CPU has it), "sse2" (two at a time) or
 * "scalar" (a build without SSE2).  Hits, counts and results are the same on
 * every path; only the speed differs. */
const char *gc_traverse_isa(void);

/* Force the timed twin's instruction set, for tests and benchmarks: "sse2",
 * "avx2" (refused on a CPU without it) or "auto" (the host's best).  Process
 * wide; not to be called while another thread traces. */
gc_status gc_traverse_set_isa(const char *isa, char *err);

/* Brute-force first hit over every triangle of the mesh (the reference). */
gc_status gc_brute_force(const gc_mesh *mesh, gc_intersector intersector, int64_t n,
                         const double *origins, const double *directions,
                         double *t, int32_t *prim, char *err);

/* Exact triangle/box overlap (separating axis test), for tests and tools. */
int gc_triangle_box_overlap(const double v0[3], const double v1[3], const double v2[3],
                            const double lo[3], const double hi[3]);

/* The scene sums of the cost model (models/stats.py defines them), one pass.
 * Bounds are over the faces' corners; e1, e2 and perimeters are per axis. */
typedef struct {
    double box_lo[3], box_hi[3];
    double e1[3];          /* sum of triangle bounding-box extents */
    double e2[3];          /* sum of areas projected along each axis */
    double perimeters[3];  /* sum of perimeters projected along each axis */
    double pair[3];        /* sum ext_y ext_z, sum ext_z ext_x, sum ext_x ext_y */
    double triple;         /* sum ext_x ext_y ext_z */
    double area;           /* total area */
    double vol6;           /* 6 x signed volume, corners taken relative to the centre of
                              all vertices' bounds (as models/stats.py does) */
    int64_t n_good;        /* triangles that are not degenerate */
} gc_mesh_sums;

/* Fill *out.  When ar_out is given, the aspect ratio longest_edge^2 / (2 area) of
 * every non-degenerate triangle whose index is a multiple of ar_stride is
 * written there (room for ceil(n_faces / ar_stride) values) and counted in *n_ar. */
gc_status gc_mesh_sums_compute(const gc_mesh *mesh, int64_t ar_stride,
                               double *ar_out, int64_t *n_ar, gc_mesh_sums *out, char *err);

/* *watertight = 1 when every edge is shared by exactly two faces, after merging
 * vertices at identical positions (-0.0 and +0.0 are one position).  Vertex ids
 * and edge offsets are 32-bit: more than 2^32 - 2 vertices or (2^32 - 2) / 3 faces
 * is GC_ERR_ARGUMENT. */
gc_status gc_mesh_watertight(const gc_mesh *mesh, int *watertight, char *err);

/* The same test, and *positions = the number of distinct vertex positions (every
 * vertex given, referenced or not, merged as above).  A mesh whose triangles share
 * their corners has about half as many positions as faces; one of separate
 * triangles has three per face. */
gc_status gc_mesh_topology(const gc_mesh *mesh, int *watertight, int64_t *positions, char *err);

/* Resolution of the monotonic clock in ns. */
int64_t gc_timer_resolution_ns(void);

#ifdef __cplusplus
}
#endif

#endif /* GRIDCAL_H */
