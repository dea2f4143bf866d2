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
 */
#include "gc_internal.h"
#include "overlap.h"

#include <float.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* Cells are widened by this fraction of their size (plus a few ulps of their
 * coordinates) when triangles are inserted, so a triangle touching a cell
 * within rounding is stored in it and traversal never misses it. */
#define GC_CELL_WIDEN_FRACTION 1e-7
#define GC_CELL_WIDEN_ULPS 8.0

typedef struct {
    gc_grid *g;
    int64_t cap_nodes, cap_cells, cap_refs;
    uint64_t limit;        /* memory limit, bytes */
    uint64_t scratch;      /* bytes of scratch held by the builders on the stack */
    const gc_build_params *p;
    char *err;
} builder;

typedef struct {
    uint32_t cell;
    uint32_t prim;
} pair;

static uint64_t grid_bytes(const builder *b)
{
    const gc_grid *g = b->g;
    return (uint64_t)g->n_tris * (sizeof(gc_tri) + sizeof(int32_t)) + (uint64_t)g->n_refs * sizeof(gc_tri) +
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

/* Cell index range [*i0, *i1] that [a, b] spans along axis `ax` of node `nd`. */
static void axis_range(const gc_node *nd, int ax, double a, double b, int32_t *i0, int32_t *i1)
{
    double fa = floor((a - nd->lo[ax]) * nd->inv_cell[ax]);
    double fb = floor((b - nd->lo[ax]) * nd->inv_cell[ax]);
    double top = (double)(nd->n[ax] - 1);
    /* NaN (a cell of zero width: a subgrid narrower than an ulp of its position) clamps to 0 */
    fa = !(fa > 0.0) ? 0.0 : (fa > top ? top : fa);
    fb = !(fb > 0.0) ? 0.0 : (fb > top ? top : fb);
    *i0 = (int32_t)fa;
    *i1 = (int32_t)fb;
}

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

/* Double the pair scratch (the rare path of collect_pairs). */
static gc_status grow_pairs(builder *b, pair **pairs, int64_t *cap)
{
    if ((uint64_t)*cap >= GC_MAX_REFS) {
        gc_set_error(b->err,
                     "more than %llu triangle references in one grid level: "
                     "the resolution is too fine for 32-bit reference offsets",
                     (unsigned long long)GC_MAX_REFS);
        return GC_ERR_OVERFLOW;
    }
    int64_t cap2 = *cap * 2;
    size_t grow = (size_t)(cap2 - *cap) * sizeof(pair);
    gc_status st = check_memory(b, grow, "the triangle references");
    if (st != GC_OK) {
        return st;
    }
    pair *p2 = realloc(*pairs, (size_t)cap2 * sizeof(pair));
    if (!p2) {
        gc_set_error(b->err, "out of memory recording triangle references");
        return GC_ERR_NO_MEMORY;
    }
    b->scratch += grow;
    *pairs = p2;
    *cap = cap2;
    return GC_OK;
}

/* Record every (cell, triangle) pair of node `nd`.  *pairs_out is scratch of
 * *cap_out entries (release with scratch_free).  The widened cell bounds, centres
 * and half sizes along each axis are tabulated once per node (cell_box). */
static gc_status collect_pairs(builder *b, const gc_node *nd, const uint32_t *prims, int64_t n_prims,
                               pair **pairs_out, int64_t *n_out, int64_t *cap_out)
{
    int64_t n = 0, cap = n_prims > 0 ? n_prims : 1;
    gc_status st;
    const int exact = b->p->insertion == GC_INSERT_EXACT;
    const int64_t n_axis = (int64_t)nd->n[0] + nd->n[1] + nd->n[2];
    const size_t tab_bytes = exact ? (size_t)n_axis * 4 * sizeof(double) : 0;
    double *tab = exact ? scratch_alloc(b, tab_bytes, "the cell bounds", &st) : NULL;
    if (exact && !tab) {
        return st;
    }
    pair *pairs = scratch_alloc(b, (size_t)cap * sizeof(pair), "the triangle references", &st);
    if (!pairs) {
        if (tab) {
            scratch_free(b, tab, tab_bytes);
        }
        return st;
    }
    /* tab: per axis i, from base[i], the cells' widened lo, hi, centre and half size */
    const double *clo[3], *chi[3], *cmid[3], *chalf[3];
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
            clo[i] = lo, chi[i] = hi, cmid[i] = mid, chalf[i] = half;
            base += nd->n[i];
        }
    }
    const int64_t nx = nd->n[0], nxy = (int64_t)nd->n[0] * nd->n[1];
    for (int64_t k = 0; k < n_prims; ++k) {
        const gc_tri *t = &b->g->tris[prims[k]];
        int32_t r0[3], r1[3];
        double bmin[3], bmax[3];
        int spread = 0; /* axes along which the bounds span several cells or leave the node */
        for (int i = 0; i < 3; ++i) {
            double a = GC_MIN(t->v0[i], GC_MIN(t->v1[i], t->v2[i]));
            double c = GC_MAX(t->v0[i], GC_MAX(t->v1[i], t->v2[i]));
            bmin[i] = a;
            bmax[i] = c;
            double w = GC_CELL_WIDEN_FRACTION * nd->cell[i] +
                       GC_CELL_WIDEN_ULPS * DBL_EPSILON * GC_MAX(fabs(a), fabs(c));
            axis_range(nd, i, a - w, c + w, &r0[i], &r1[i]);
            spread += (r0[i] != r1[i]) | (a - w < nd->lo[i]) | (c + w > nd->hi[i]);
        }
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
                    goto fail;
                }
            }
            for (int32_t z = r0[2]; z <= r1[2]; ++z) {
                for (int32_t y = r0[1]; y <= r1[1]; ++y) {
                    for (int32_t x = r0[0]; x <= r1[0]; ++x) {
                        if (row && ((bmin[0] > chi[0][x]) | (bmax[0] < clo[0][x]) | (bmin[1] > chi[1][y]) |
                                    (bmax[1] < clo[1][y]) | (bmin[2] > chi[2][z]) | (bmax[2] < clo[2][z]))) {
                            continue;
                        }
                        pairs[n].cell = (uint32_t)(x + nx * y + nxy * z);
                        pairs[n].prim = prims[k];
                        ++n;
                    }
                }
            }
            continue;
        }
        gc_tri_box_prep prep;
        gc_tri_box_prepare(&prep, t->v0, t->v1, t->v2);
        for (int32_t z = r0[2]; z <= r1[2]; ++z) {
            const double lo2 = clo[2][z], hi2 = chi[2][z], m2 = cmid[2][z], h2 = chalf[2][z];
            for (int32_t y = r0[1]; y <= r1[1]; ++y) {
                const double lo1 = clo[1][y], hi1 = chi[1][y], m1 = cmid[1][y], h1 = chalf[1][y];
                for (int32_t x = r0[0]; x <= r1[0]; ++x) {
                    if (!gc_tri_box_prepared_overlap(&prep, clo[0][x], lo1, lo2, chi[0][x], hi1, hi2,
                                                     cmid[0][x], m1, m2, chalf[0][x], h1, h2)) {
                        continue;
                    }
                    if (n == cap && (st = grow_pairs(b, &pairs, &cap)) != GC_OK) {
                        goto fail;
                    }
                    pairs[n].cell = (uint32_t)(x + nx * y + nxy * z);
                    pairs[n].prim = prims[k];
                    ++n;
                }
            }
        }
    }
    if (tab) {
        scratch_free(b, tab, tab_bytes);
    }
    *pairs_out = pairs;
    *n_out = n;
    *cap_out = cap;
    return GC_OK;
fail:
    scratch_free(b, pairs, (size_t)cap * sizeof(pair));
    if (tab) {
        scratch_free(b, tab, tab_bytes);
    }
    return st;
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
    st = reserve(b, (void **)&g->cells, &b->cap_cells, g->n_cells + ncell, sizeof(gc_cell), "the cells");
    if (st != GC_OK) {
        return st;
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
    pair *pairs = NULL;
    int64_t n_pairs = 0, cap_pairs = 0;
    st = collect_pairs(b, &nd, prims, n_prims, &pairs, &n_pairs, &cap_pairs);
    if (st != GC_OK) {
        return st;
    }
    size_t off_bytes = (size_t)(ncell + 1) * sizeof(uint32_t);
    size_t sorted_bytes = (size_t)(n_pairs > 0 ? n_pairs : 1) * sizeof(uint32_t);
    uint32_t *off = scratch_alloc(b, off_bytes, "the cell offsets", &st);
    uint32_t *sorted = off ? scratch_alloc(b, sorted_bytes, "the sorted references", &st) : NULL;
    if (!sorted) {
        if (off) {
            scratch_free(b, off, off_bytes);
        }
        scratch_free(b, pairs, (size_t)cap_pairs * sizeof(pair));
        return st;
    }
    memset(off, 0, off_bytes);
    for (int64_t k = 0; k < n_pairs; ++k) {
        off[pairs[k].cell + 1]++;
    }
    for (int64_t c = 0; c < ncell; ++c) {
        off[c + 1] += off[c];
    }
    for (int64_t k = 0; k < n_pairs; ++k) {
        sorted[off[pairs[k].cell]++] = pairs[k].prim;
    }
    for (int64_t c = ncell; c > 0; --c) { /* the scatter advanced each offset to its end */
        off[c] = off[c - 1];
    }
    off[0] = 0;
    scratch_free(b, pairs, (size_t)cap_pairs * sizeof(pair));

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

/* Spread the low 21 bits of x to every third bit (Morton encoding). */
static uint64_t spread_bits(uint64_t x)
{
    x &= 0x1fffff;
    x = (x | x << 32) & 0x1f00000000ffffull;
    x = (x | x << 16) & 0x1f0000ff0000ffull;
    x = (x | x << 8) & 0x100f00f00f00f00full;
    x = (x | x << 4) & 0x10c30c30c30c30c3ull;
    x = (x | x << 2) & 0x1249249249249249ull;
    return x;
}

typedef struct {
    uint64_t key;
    uint32_t index;
    uint32_t pad;
} keyed;

/* The mesh's faces in Morton order of their centroids within [lo, hi], by an
 * LSD radix sort (stable, so equal codes keep the mesh's order).  order
 * receives n face indices. */
static gc_status morton_order(builder *b, const gc_mesh *mesh, const double lo[3], const double hi[3],
                              uint32_t *order)
{
    const int64_t n = mesh->n_faces;
    size_t bytes = (size_t)(n > 0 ? n : 1) * sizeof(keyed);
    gc_status st;
    keyed *a = scratch_alloc(b, bytes, "the triangle order", &st);
    keyed *tmp = a ? scratch_alloc(b, bytes, "the triangle order", &st) : NULL;
    if (!tmp) {
        if (a) {
            scratch_free(b, a, bytes);
        }
        return st;
    }
    const double scale = (double)(1u << 21) - 1.0;
    for (int64_t f = 0; f < n; ++f) {
        uint64_t q[3];
        for (int i = 0; i < 3; ++i) {
            double c = (mesh->vertices[3 * mesh->faces[3 * f] + i] + mesh->vertices[3 * mesh->faces[3 * f + 1] + i] +
                        mesh->vertices[3 * mesh->faces[3 * f + 2] + i]) /
                       3.0;
            double u = (c - lo[i]) / (hi[i] - lo[i]) * scale;
            u = u > 0.0 ? (u < scale ? u : scale) : 0.0;
            q[i] = (uint64_t)u;
        }
        a[f].key = spread_bits(q[0]) | spread_bits(q[1]) << 1 | spread_bits(q[2]) << 2;
        a[f].index = (uint32_t)f;
        a[f].pad = 0;
    }
    enum { DIGIT_BITS = 11, BUCKETS = 1 << DIGIT_BITS, PASSES = 6 }; /* 66 >= 63 key bits */
    static const int digit_mask = BUCKETS - 1;
    for (int pass = 0; pass < PASSES; ++pass) {
        int64_t count[BUCKETS + 1];
        memset(count, 0, sizeof count);
        const int shift = pass * DIGIT_BITS;
        for (int64_t k = 0; k < n; ++k) {
            count[((a[k].key >> shift) & (uint64_t)digit_mask) + 1]++;
        }
        for (int d = 0; d < BUCKETS; ++d) {
            count[d + 1] += count[d];
        }
        for (int64_t k = 0; k < n; ++k) {
            tmp[count[(a[k].key >> shift) & (uint64_t)digit_mask]++] = a[k];
        }
        keyed *sw = a;
        a = tmp;
        tmp = sw;
    }
    for (int64_t k = 0; k < n; ++k) {
        order[k] = a[k].index;
    }
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

gc_status gc_grid_build(const gc_mesh *mesh, const gc_build_params *params, gc_grid **out, char *err)
{
    *out = NULL;
    gc_build_params p = params ? *params : gc_build_params_default();
    gc_status st = check_params(&p, err);
    if (st != GC_OK) {
        return st;
    }
    st = gc_check_mesh(mesh, p.has_box, err);
    if (st != GC_OK) {
        return st;
    }
    double lo[3], hi[3];
    if (p.has_box) {
        for (int i = 0; i < 3; ++i) {
            lo[i] = p.box_lo[i];
            hi[i] = p.box_hi[i];
        }
        for (int64_t k = 0; k < 3 * mesh->n_faces; ++k) {
            const double *v = mesh->vertices + 3 * mesh->faces[k];
            for (int i = 0; i < 3; ++i) {
                if (!(v[i] >= lo[i] && v[i] <= hi[i])) {
                    gc_set_error(err, "vertex %lld lies outside the given grid box",
                                 (long long)mesh->faces[k]);
                    return GC_ERR_ARGUMENT;
                }
            }
        }
    } else {
        gc_mesh_box_checked(mesh, lo, hi); /* gc_check_mesh refused a mesh without faces */
    }
    /* Cell sizes and cell indices divide by the extent: an extent that overflows to
     * inf would turn them into NaN and the cell index into anything. */
    for (int i = 0; i < 3; ++i) {
        if (!isfinite(hi[i] - lo[i])) {
            gc_set_error(err, "the grid box is too wide for double precision: its extent on axis %d overflows", i);
            return GC_ERR_ARGUMENT;
        }
    }

    builder b;
    memset(&b, 0, sizeof b);
    b.limit = p.memory_limit_bytes ? p.memory_limit_bytes : GC_DEFAULT_MEMORY_LIMIT_BYTES;
    b.p = &p;
    b.err = err;
    gc_grid *g = calloc(1, sizeof *g);
    if (!g) {
        gc_set_error(err, "out of memory");
        return GC_ERR_NO_MEMORY;
    }
    b.g = g;
    g->intersector = p.intersector;
    g->mailbox = p.mailbox != 0;
    g->n_tris = mesh->n_faces;

    st = check_resolution(&b, p.resolution, 0);
    uint32_t *prims = NULL;
    size_t prims_bytes = (size_t)(g->n_tris > 0 ? g->n_tris : 1) * sizeof(uint32_t);
    if (st == GC_OK) {
        st = check_memory(&b, 0, "the triangles"); /* grid_bytes counts them already */
    }
    if (st == GC_OK) {
        size_t n_alloc = (size_t)(g->n_tris > 0 ? g->n_tris : 1);
        g->tris = malloc(n_alloc * sizeof(gc_tri));
        g->tri_id = malloc(n_alloc * sizeof(int32_t));
        if (!g->tris || !g->tri_id) {
            gc_set_error(err, "out of memory copying %lld triangles", (long long)g->n_tris);
            st = GC_ERR_NO_MEMORY;
        }
    }
    if (st == GC_OK) {
        prims = scratch_alloc(&b, prims_bytes, "the triangle list", &st);
    }
    if (st == GC_OK) {
        st = morton_order(&b, mesh, lo, hi, prims);
        if (st != GC_OK) {
            scratch_free(&b, prims, prims_bytes);
        }
    }
    if (st == GC_OK) {
        for (int64_t k = 0; k < g->n_tris; ++k) {
            const int64_t *fv = mesh->faces + 3 * (int64_t)prims[k];
            memcpy(g->tris[k].v0, mesh->vertices + 3 * fv[0], 3 * sizeof(double));
            memcpy(g->tris[k].v1, mesh->vertices + 3 * fv[1], 3 * sizeof(double));
            memcpy(g->tris[k].v2, mesh->vertices + 3 * fv[2], 3 * sizeof(double));
            g->tri_id[k] = (int32_t)prims[k];
            prims[k] = (uint32_t)k; /* the top level indexes the stored (sorted) triangles */
        }
        uint32_t top;
        st = build_node(&b, prims, g->n_tris, lo, hi, p.resolution, 0, &top);
        scratch_free(&b, prims, prims_bytes);
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
        b.cap_refs = g->n_refs;
    }
    st = check_memory(&b, GC_PACK_BYTES(g->n_refs), "the per-reference triangles");
    if (st == GC_OK) {
        g->ref_tris = calloc((size_t)GC_PACK_BYTES(g->n_refs > 0 ? g->n_refs : 1), 1);
        if (!g->ref_tris) {
            gc_set_error(err, "out of memory copying %lld triangle references", (long long)g->n_refs);
            st = GC_ERR_NO_MEMORY;
        }
    }
    if (st != GC_OK) {
        gc_grid_free(g);
        return st;
    }
    for (int64_t k = 0; k < g->n_refs; ++k) {
        const gc_tri *t = &g->tris[g->refs[k]];
        gc_pack *pk = &g->ref_tris[k / GC_LANES];
        const int lane = (int)(k % GC_LANES);
        for (int i = 0; i < 3; ++i) {
            pk->c[i][lane] = t->v0[i];
            pk->c[3 + i][lane] = t->v1[i];
            pk->c[6 + i][lane] = t->v2[i];
        }
    }
    free(g->tris);
    g->tris = NULL;
    *out = g;
    return GC_OK;
}
