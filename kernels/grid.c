/* grid.c - grid lifetime, defaults, the grid box rule, input checks, info. */
#define _POSIX_C_SOURCE 199309L
#include "gc_internal.h"

#include <float.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

/* A degenerate axis is widened to this fraction of the longest one, so cells
 * stay finite and a flat scene still gets a proper 3D grid. */
#define GC_MIN_AXIS_FRACTION 1e-3
/* With every vertex at one point: half-width relative to the coordinates ... */
#define GC_POINT_BOX_RELATIVE 1e-6
/* ... and the absolute floor when that point is the origin. */
#define GC_POINT_BOX_ABSOLUTE 1e-300

void gc_set_error(char *err, const char *fmt, ...)
{
    if (!err) {
        return;
    }
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(err, GC_ERROR_LEN, fmt, ap);
    va_end(ap);
}

gc_build_params gc_build_params_default(void)
{
    gc_build_params p;
    memset(&p, 0, sizeof p);
    p.resolution[0] = p.resolution[1] = p.resolution[2] = 1;
    p.intersector = GC_WATERTIGHT;
    p.insertion = GC_INSERT_EXACT;
    p.mailbox = 0;
    p.has_box = 0;
    p.memory_limit_bytes = 0;
    p.levels = 1;
    p.subdivide_threshold = 2;
    for (int d = 0; d < GC_MAX_LEVELS; ++d) {
        p.level_scale[d] = 8.0; /* Manta RecursiveGrid's "found 8 to work well" */
        p.level_exponent[d] = 1.0;
    }
    p.subgrid_resolutions = NULL;
    p.subgrid_resolutions2 = NULL;
    p.n_subgrid_resolutions2 = 0;
    p.rule_max_axis = 256;
    p.threads = 1;
    return p;
}

void gc_widen_box(double lo[3], double hi[3])
{
    double emax = 0.0, amax = 0.0;
    for (int i = 0; i < 3; ++i) {
        emax = fmax(emax, hi[i] - lo[i]);
        amax = fmax(amax, fmax(fabs(lo[i]), fabs(hi[i])));
    }
    double floor_width = emax > 0.0 ? emax * GC_MIN_AXIS_FRACTION
                                    : fmax(amax * GC_POINT_BOX_RELATIVE, GC_POINT_BOX_ABSOLUTE);
    for (int i = 0; i < 3; ++i) {
        double e = hi[i] - lo[i];
        if (e < floor_width) {
            double c = 0.5 * (lo[i] + hi[i]);
            lo[i] = c - 0.5 * floor_width;
            hi[i] = c + 0.5 * floor_width;
        }
    }
}

gc_status gc_check_mesh_shape(const gc_mesh *mesh, int allow_empty, char *err)
{
    if (!mesh) {
        gc_set_error(err, "no mesh given");
        return GC_ERR_ARGUMENT;
    }
    if (mesh->n_faces < 0 || mesh->n_vertices < 0) {
        gc_set_error(err, "negative vertex or face count");
        return GC_ERR_ARGUMENT;
    }
    if (mesh->n_faces == 0) {
        if (allow_empty) {
            return GC_OK;
        }
        gc_set_error(err, "the mesh has no faces");
        return GC_ERR_ARGUMENT;
    }
    if (!mesh->faces || !mesh->vertices || mesh->n_vertices == 0) {
        gc_set_error(err, "the mesh has faces but no vertices");
        return GC_ERR_ARGUMENT;
    }
    if ((uint64_t)mesh->n_faces > (uint64_t)INT32_MAX) {
        gc_set_error(err, "%lld faces exceed the limit of %d", (long long)mesh->n_faces, INT32_MAX);
        return GC_ERR_OVERFLOW;
    }
    return GC_OK;
}

gc_status gc_check_mesh(const gc_mesh *mesh, int allow_empty, double lo[3], double hi[3], char *err)
{
    gc_status st = gc_check_mesh_shape(mesh, allow_empty, err);
    if (st != GC_OK || mesh->n_faces == 0) {
        return st;
    }
    double l0 = INFINITY, l1 = INFINITY, l2 = INFINITY;
    double h0 = -INFINITY, h1 = -INFINITY, h2 = -INFINITY;
    const int64_t *f = mesh->faces;
    for (int64_t k = 0; k < 3 * mesh->n_faces; ++k) {
        int64_t v = f[k];
        if (v < 0 || v >= mesh->n_vertices) {
            gc_set_error(err, "face %lld refers to vertex %lld, outside [0, %lld)", (long long)(k / 3),
                         (long long)v, (long long)mesh->n_vertices);
            return GC_ERR_ARGUMENT;
        }
        const double *p = mesh->vertices + 3 * v;
        /* x - x is 0 for a finite x and NaN for an infinite or NaN one */
        if (!((p[0] - p[0]) + (p[1] - p[1]) + (p[2] - p[2]) == 0.0)) {
            gc_set_error(err, "vertex %lld (used by face %lld) is not finite", (long long)v,
                         (long long)(k / 3));
            return GC_ERR_ARGUMENT;
        }
        l0 = GC_MIN(l0, p[0]);
        l1 = GC_MIN(l1, p[1]);
        l2 = GC_MIN(l2, p[2]);
        h0 = GC_MAX(h0, p[0]);
        h1 = GC_MAX(h1, p[1]);
        h2 = GC_MAX(h2, p[2]);
    }
    if (lo && hi) { /* the bounds of the vertices that faces use, in the same pass */
        lo[0] = l0, lo[1] = l1, lo[2] = l2;
        hi[0] = h0, hi[1] = h1, hi[2] = h2;
    }
    return GC_OK;
}

gc_status gc_mesh_box(const gc_mesh *mesh, double lo[3], double hi[3], char *err)
{
    gc_status st = gc_check_mesh(mesh, 0, lo, hi, err);
    if (st != GC_OK) {
        return st;
    }
    gc_widen_box(lo, hi);
    return GC_OK;
}

void gc_grid_free(gc_grid *grid)
{
    if (!grid) {
        return;
    }
    gc_big_free(grid->ref_tris, grid->ref_tris_mapped);
    free(grid->nodes);
    gc_big_free(grid->cells, grid->cells_mapped);
    gc_big_free(grid->occ ? grid->occ - grid->occ_pad : NULL, grid->occ_mapped);
    free(grid->refs);
    free(grid);
}

void gc_grid_get_info(const gc_grid *g, gc_grid_info *info)
{
    memset(info, 0, sizeof *info);
    info->n_triangles = g->n_tris;
    info->n_nodes = g->n_nodes;
    info->n_cells = g->n_cells;
    info->n_refs = g->n_refs;
    int64_t empty = 0;
    uint32_t deepest = 0;
    for (int64_t c = 0; c < g->n_cells; ++c) {
        empty += g->cells[c].count == 0;
    }
    for (int64_t k = 0; k < g->n_nodes; ++k) {
        if (g->nodes[k].depth > deepest) {
            deepest = g->nodes[k].depth;
        }
    }
    info->n_empty_cells = empty;
    info->memory_bytes = (int64_t)(sizeof(gc_grid) + (size_t)GC_PACK_BYTES(g->n_refs) +
                                   (size_t)g->n_nodes * sizeof(gc_node) +
                                   (size_t)g->n_cells * sizeof(gc_cell) +
                                   (size_t)(GC_OCC_WORDS(g->n_cells) + 2 * (uint64_t)g->occ_pad) *
                                       sizeof(uint64_t));
    info->levels = (int32_t)deepest + 1;
    for (int i = 0; i < 3; ++i) {
        info->resolution[i] = g->nodes[0].n[i];
        info->box_lo[i] = g->nodes[0].lo[i];
        info->box_hi[i] = g->nodes[0].hi[i];
    }
    info->intersector = g->intersector;
    info->mailbox = g->mailbox;
}

static int64_t subtree_refs(const gc_grid *g, const gc_cell *cell)
{
    if (cell->count != GC_CELL_SUBGRID) {
        return cell->count;
    }
    const gc_node *child = &g->nodes[cell->begin];
    int64_t total = 0, ncell = (int64_t)child->n[0] * child->n[1] * child->n[2];
    for (int64_t c = 0; c < ncell; ++c) {
        total += subtree_refs(g, &g->cells[child->first_cell + c]);
    }
    return total;
}

void gc_grid_top_counts(const gc_grid *g, int64_t *counts)
{
    const gc_node *top = &g->nodes[0];
    int64_t ncell = (int64_t)top->n[0] * top->n[1] * top->n[2];
    for (int64_t c = 0; c < ncell; ++c) {
        counts[c] = subtree_refs(g, &g->cells[top->first_cell + c]);
    }
}

gc_status gc_check_rays(int64_t n, const double *origins, const double *directions, char *err)
{
    if (n < 0) {
        gc_set_error(err, "negative ray count %lld", (long long)n);
        return GC_ERR_ARGUMENT;
    }
    if (n > 0 && (!origins || !directions)) {
        gc_set_error(err, "ray arrays are missing");
        return GC_ERR_ARGUMENT;
    }
    for (int64_t k = 0; k < n; ++k) {
        const double *o = origins + 3 * k, *d = directions + 3 * k;
        /* x - x is 0 for a finite x and NaN for an infinite or NaN one */
        if (!((o[0] - o[0]) + (o[1] - o[1]) + (o[2] - o[2]) + (d[0] - d[0]) + (d[1] - d[1]) + (d[2] - d[2]) ==
              0.0)) {
            gc_set_error(err, "ray %lld has a non-finite origin or direction", (long long)k);
            return GC_ERR_ARGUMENT;
        }
        if (d[0] == 0.0 && d[1] == 0.0 && d[2] == 0.0) {
            gc_set_error(err, "ray %lld has a zero direction", (long long)k);
            return GC_ERR_ARGUMENT;
        }
    }
    return GC_OK;
}

int64_t gc_timer_resolution_ns(void)
{
    struct timespec ts;
    if (clock_getres(CLOCK_MONOTONIC, &ts) != 0) {
        return -1;
    }
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}
