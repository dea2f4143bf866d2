/* bench_traverse.c - standalone speed benchmark of the kernels (no Python).
 *
 * Builds grids over procedural meshes made here (a geodesic icosphere, the
 * talk's closed cylinder of full-length side triangles) and traces random rays
 * from outside the box towards random points inside it, one core.  Prints per
 * case: build time and build references per second (best of a few builds, wall
 * time), wall ns per ray of the timed twin (best of a few batches), and the
 * same two rates from the process's CPU time (best of the same runs), which a
 * loaded host disturbs less.  Instructions per
 * ray come from running it under callgrind (`make profile`): the figure printed
 * there is the total Ir of the traversal divided by the number of rays.
 *
 *   bench_traverse [rays] [repeats] [case]
 *
 * rays: rays per batch (default 100000); repeats: builds and batches timed
 * (default 5); case: run only the cases whose name contains this string.
 * Everything is seeded: two runs trace the same rays.
 */
#define _POSIX_C_SOURCE 199309L
#include "gc_internal.h"
#include "gridcal.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef struct {
    double *v;
    int64_t nv;
    int64_t *f;
    int64_t nf;
} mesh;

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* CPU time of this process: on a loaded host it leaves out the time the
 * process waited for a core (though not what sharing the caches costs). */
static double cpu_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* splitmix64: a small seeded generator */
static uint64_t rng_state;
static uint64_t rng_next(void)
{
    uint64_t z = (rng_state += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
}
static double rng_unit(void) { return (double)(rng_next() >> 11) * (1.0 / 9007199254740992.0); }

static void *xmalloc(size_t n)
{
    void *p = malloc(n ? n : 1);
    if (!p) {
        fprintf(stderr, "bench_traverse: out of memory\n");
        exit(1);
    }
    return p;
}

/* Geodesic icosphere of frequency f: 20 f^2 triangles; each icosahedron face is
 * split into an f x f lattice projected on the unit sphere.  A triangle soup (3
 * own vertices per triangle): the traversal does not care about sharing. */
static mesh make_icosphere(int f)
{
    const double p = (1.0 + sqrt(5.0)) / 2.0;
    const double ico[12][3] = {{-1, p, 0}, {1, p, 0}, {-1, -p, 0}, {1, -p, 0}, {0, -1, p}, {0, 1, p},
                               {0, -1, -p}, {0, 1, -p}, {p, 0, -1}, {p, 0, 1}, {-p, 0, -1}, {-p, 0, 1}};
    const int faces[20][3] = {{0, 11, 5}, {0, 5, 1}, {0, 1, 7},   {0, 7, 10}, {0, 10, 11},
                              {1, 5, 9},  {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                              {3, 9, 4},  {3, 4, 2},  {3, 2, 6},   {3, 6, 8},  {3, 8, 9},
                              {4, 9, 5},  {2, 4, 11}, {6, 2, 10},  {8, 6, 7},  {9, 8, 1}};
    mesh m;
    m.nf = 20 * (int64_t)f * f;
    m.nv = 3 * m.nf;
    m.v = xmalloc((size_t)m.nv * 3 * sizeof(double));
    m.f = xmalloc((size_t)m.nf * 3 * sizeof(int64_t));
    int64_t t = 0;
    for (int k = 0; k < 20; ++k) {
        const double *A = ico[faces[k][0]], *B = ico[faces[k][1]], *C = ico[faces[k][2]];
        for (int i = 0; i < f; ++i) {
            for (int j = 0; j < f - i; ++j) {
                /* lattice point (i, j) = A + i/f (B - A) + j/f (C - A) */
                int tri[2][3][2] = {{{i, j}, {i + 1, j}, {i, j + 1}}, {{i + 1, j}, {i + 1, j + 1}, {i, j + 1}}};
                int ntri = (j < f - i - 1) ? 2 : 1;
                for (int q = 0; q < ntri; ++q) {
                    for (int c = 0; c < 3; ++c) {
                        double a = (double)tri[q][c][0] / f, b = (double)tri[q][c][1] / f;
                        double x[3], n2 = 0.0;
                        for (int d = 0; d < 3; ++d) {
                            x[d] = A[d] + a * (B[d] - A[d]) + b * (C[d] - A[d]);
                            n2 += x[d] * x[d];
                        }
                        double s = 1.0 / sqrt(n2);
                        for (int d = 0; d < 3; ++d) {
                            m.v[3 * (3 * t + c) + d] = x[d] * s;
                        }
                        m.f[3 * t + c] = 3 * t + c;
                    }
                    ++t;
                }
            }
        }
    }
    if (t != m.nf) {
        fprintf(stderr, "bench_traverse: icosphere made %lld triangles, not %lld\n", (long long)t,
                (long long)m.nf);
        exit(1);
    }
    return m;
}

/* The talk's closed cylinder (calibrate/scenes.py cylinder_mesh): radius 1, axis
 * z from 0 to 10, n ring vertices, side quads split into two full-length
 * triangles, fan caps: 4 n - 4 triangles. */
static mesh make_cylinder(int n)
{
    mesh m;
    m.nv = 2 * (int64_t)n;
    m.nf = 4 * (int64_t)n - 4;
    m.v = xmalloc((size_t)m.nv * 3 * sizeof(double));
    m.f = xmalloc((size_t)m.nf * 3 * sizeof(int64_t));
    const double pi = 3.14159265358979323846;
    for (int i = 0; i < n; ++i) {
        double th = 2.0 * pi * i / n;
        for (int e = 0; e < 2; ++e) {
            double *v = m.v + 3 * (e * n + i);
            v[0] = cos(th);
            v[1] = sin(th);
            v[2] = e ? 10.0 : 0.0;
        }
    }
    int64_t t = 0;
    for (int i = 0; i < n; ++i) {
        int j = (i + 1) % n;
        int64_t q[2][3] = {{i, j, n + j}, {i, n + j, n + i}};
        for (int k = 0; k < 2; ++k, ++t) {
            memcpy(m.f + 3 * t, q[k], sizeof q[k]);
        }
    }
    for (int i = 1; i + 1 < n; ++i, ++t) { /* bottom fan, facing -z */
        int64_t q[3] = {0, i + 1, i};
        memcpy(m.f + 3 * t, q, sizeof q);
    }
    for (int i = 1; i + 1 < n; ++i, ++t) { /* top fan, facing +z */
        int64_t q[3] = {n, n + i, n + i + 1};
        memcpy(m.f + 3 * t, q, sizeof q);
    }
    return m;
}

/* Rays from a sphere around the box (twice its half-diagonal) towards uniform
 * points inside the box. */
static void make_rays(const double lo[3], const double hi[3], int64_t n, uint64_t seed, double *o, double *d)
{
    rng_state = seed;
    double c[3], r = 0.0;
    for (int i = 0; i < 3; ++i) {
        c[i] = 0.5 * (lo[i] + hi[i]);
        r += 0.25 * (hi[i] - lo[i]) * (hi[i] - lo[i]);
    }
    r = 2.0 * sqrt(r);
    for (int64_t k = 0; k < n; ++k) {
        double u = 2.0 * rng_unit() - 1.0, ph = 2.0 * 3.14159265358979323846 * rng_unit();
        double s = sqrt(1.0 - u * u);
        double dir[3] = {s * cos(ph), s * sin(ph), u};
        double tgt[3];
        for (int i = 0; i < 3; ++i) {
            o[3 * k + i] = c[i] + r * dir[i];
            tgt[i] = lo[i] + (hi[i] - lo[i]) * rng_unit();
            d[3 * k + i] = tgt[i] - o[3 * k + i];
        }
    }
}

/* Resolution for about `cells` near-cubic cells over extents ext (as calibrate/_grid.py). */
static void resolution_for(double cells, const double ext[3], int32_t res[3])
{
    double lv = log(ext[0]) + log(ext[1]) + log(ext[2]);
    for (int i = 0; i < 3; ++i) {
        double r = floor(exp(log(ext[i]) + (log(cells) - lv) / 3.0) + 0.5);
        res[i] = r < 1.0 ? 1 : (int32_t)r;
    }
}

/* FNV-1a digest of the grid's cells and the face index of each reference: two
 * builds that store the same references in the same order have the same digest. */
static uint64_t grid_digest(const gc_grid *g)
{
    uint64_t h = 1469598103934665603ull;
    const unsigned char *p = (const unsigned char *)g->cells;
    for (size_t k = 0; k < (size_t)g->n_cells * sizeof(gc_cell); ++k) {
        h = (h ^ p[k]) * 1099511628211ull;
    }
    for (int64_t k = 0; k < g->n_refs; ++k) {
        const int32_t id = g->ref_tris[k / GC_LANES].id[k % GC_LANES];
        p = (const unsigned char *)&id;
        for (size_t b = 0; b < sizeof id; ++b) {
            h = (h ^ p[b]) * 1099511628211ull;
        }
    }
    return h;
}

typedef struct {
    const char *name;
    int scene;      /* 0 icosphere, 1 cylinder */
    int size;       /* frequency or segments */
    double density; /* top-level cells per triangle */
    int levels;
    gc_intersector isect;
} bench_case;

static const bench_case CASES[] = {
    {"sphere82k_1N_wt", 0, 64, 1.0, 1, GC_WATERTIGHT},
    {"sphere82k_1N_mt", 0, 64, 1.0, 1, GC_MOLLER_TRUMBORE},
    {"sphere82k_2lvl_wt", 0, 64, 1.0 / 8.0, 2, GC_WATERTIGHT},
    {"cylinder8k_1N_wt", 1, 2001, 1.0, 1, GC_WATERTIGHT},
    {"cylinder8k_1N_mt", 1, 2001, 1.0, 1, GC_MOLLER_TRUMBORE},
    {"cylinder8k_2lvl_wt", 1, 2001, 1.0 / 8.0, 2, GC_WATERTIGHT},
    /* the talk's cylinder1996 at about the resolution calibrate bench recommends
     * (35x35x172): nearly one reference per cell, so steps dominate */
    {"cylinder2k_100N_wt", 1, 500, 100.0, 1, GC_WATERTIGHT},
    /* about the cells per triangle calibrate bench recommends for compact scans
     * (3.4 to 3.6): more empty cells, fewer tests per cell (last, so that the
     * cases above keep their rays' seeds) */
    {"sphere82k_3N_wt", 0, 64, 3.5, 1, GC_WATERTIGHT},
};

int main(int argc, char **argv)
{
    const int64_t n_rays = argc > 1 ? atoll(argv[1]) : 100000;
    const int repeats = argc > 2 ? atoi(argv[2]) : 5;
    const char *only = argc > 3 ? argv[3] : NULL;
    if (n_rays < 1 || repeats < 1) {
        fprintf(stderr, "usage: bench_traverse [rays >= 1] [repeats >= 1] [case]\n");
        return 2;
    }
    char err[GC_ERROR_LEN];
    double *o = xmalloc((size_t)n_rays * 3 * sizeof(double));
    double *d = xmalloc((size_t)n_rays * 3 * sizeof(double));
    printf("%-20s %8s %6s %14s %9s %10s %9s %9s %9s %9s %11s\n", "case", "tris", "levels", "resolution",
           "refs", "build_ms", "Mrefs/s", "ns/ray", "Mrays/s", "cpuMref/s", "cpu_ns/ray");
    for (size_t ci = 0; ci < sizeof CASES / sizeof CASES[0]; ++ci) {
        const bench_case *bc = &CASES[ci];
        if (only && !strstr(bc->name, only)) {
            continue;
        }
        mesh m = bc->scene == 0 ? make_icosphere(bc->size) : make_cylinder(bc->size);
        gc_mesh gm = {m.v, m.nv, m.f, m.nf};
        double lo[3], hi[3], ext[3];
        if (gc_mesh_box(&gm, lo, hi, err) != GC_OK) {
            fprintf(stderr, "bench_traverse: %s\n", err);
            return 1;
        }
        for (int i = 0; i < 3; ++i) {
            ext[i] = hi[i] - lo[i];
        }
        gc_build_params p = gc_build_params_default();
        resolution_for(bc->density * (double)m.nf, ext, p.resolution);
        p.intersector = bc->isect;
        p.levels = bc->levels;
        if (bc->levels > 1) { /* Manta's rule, as calibrate/_grid.py sets it */
            for (int k = 0; k < bc->levels; ++k) {
                p.level_scale[k] = 8.0;
                p.level_exponent[k] = 3.0 / (2 * bc->levels + 1 - 2 * k);
            }
        }
        gc_grid *g = NULL;
        double best_build = INFINITY, best_build_cpu = INFINITY;
        for (int rep = 0; rep < repeats; ++rep) {
            if (g) {
                gc_grid_free(g);
            }
            double t0 = now_s(), c0 = cpu_s();
            if (gc_grid_build(&gm, &p, &g, err) != GC_OK) {
                fprintf(stderr, "bench_traverse: %s: %s\n", bc->name, err);
                return 1;
            }
            double dt = now_s() - t0, dc = cpu_s() - c0;
            best_build = dt < best_build ? dt : best_build;
            best_build_cpu = dc < best_build_cpu ? dc : best_build_cpu;
        }
        gc_grid_info info;
        gc_grid_get_info(g, &info);
        make_rays(lo, hi, n_rays, 1000 + ci, o, d);
        double best = INFINITY, best_cpu = INFINITY, checksum = 0.0;
        for (int rep = 0; rep < repeats; ++rep) {
            int64_t ns;
            double c0 = cpu_s();
            if (gc_bench_intersect(g, n_rays, o, d, 1, &ns, &checksum, err) != GC_OK) {
                fprintf(stderr, "bench_traverse: %s: %s\n", bc->name, err);
                return 1;
            }
            double dc = 1e9 * (cpu_s() - c0);
            best = (double)ns < best ? (double)ns : best;
            best_cpu = dc < best_cpu ? dc : best_cpu;
        }
        char res[32];
        snprintf(res, sizeof res, "%dx%dx%d", p.resolution[0], p.resolution[1], p.resolution[2]);
        printf("%-20s %8lld %6d %14s %9lld %10.2f %9.2f %9.1f %9.3f %9.2f %11.1f  (checksum %.15e, grid %016llx)\n", bc->name,
               (long long)m.nf, info.levels, res, (long long)info.n_refs, 1e3 * best_build,
               1e-6 * (double)info.n_refs / best_build, best / (double)n_rays, 1e3 * (double)n_rays / best,
               1e-6 * (double)info.n_refs / best_build_cpu, best_cpu / (double)n_rays, checksum, (unsigned long long)grid_digest(g));
        fflush(stdout);
        gc_grid_free(g);
        free(m.v);
        free(m.f);
    }
    free(o);
    free(d);
    return 0;
}
