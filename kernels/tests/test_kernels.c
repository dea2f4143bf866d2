/* test_kernels.c - the kernels tested on their own, without Python.
 *
 * Every grid's first hits are compared with brute force; the timed and
 * instrumented twins must agree exactly; bad input and oversized resolutions
 * must be refused with a message.  Random cases are seeded by their index.
 * Run under AddressSanitizer and UndefinedBehaviorSanitizer by
 * `make test-sanitize`.
 */
#include "box.h"         /* the box clips, scalar and AVX2 */
#include "gc_internal.h" /* gc_big_calloc, gc_big_move, the ray preparations */
#include "gridcal.h"
#include "overlap.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define PI 3.14159265358979323846

static int failures = 0;
static int checks = 0;

#define CHECK(cond, ...)                                                                           \
    do {                                                                                           \
        ++checks;                                                                                  \
        if (!(cond)) {                                                                             \
            ++failures;                                                                            \
            fprintf(stderr, "FAIL %s:%d: ", __FILE__, __LINE__);                                   \
            fprintf(stderr, __VA_ARGS__);                                                          \
            fprintf(stderr, "\n");                                                                 \
        }                                                                                          \
    } while (0)

/* xorshift64*: a small seeded generator so every case names its reproduction */
static uint64_t rng_state;
static void rng_seed(uint64_t s) { rng_state = s * 0x9E3779B97F4A7C15ull + 1; }
static double rng_uniform(void)
{
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    return (double)((rng_state * 2685821657736338717ull) >> 11) * (1.0 / 9007199254740992.0);
}

typedef struct {
    double *v;
    int64_t *f;
    int64_t nv, nf;
} mesh_buf;

static void mesh_free(mesh_buf *m)
{
    free(m->v);
    free(m->f);
}

static gc_mesh as_mesh(const mesh_buf *m)
{
    gc_mesh g = {m->v, m->nv, m->f, m->nf};
    return g;
}

/* A closed UV sphere of radius `rad`, with shared vertices and jittered radius. */
static mesh_buf uv_sphere(int rings, int segs, double rad, double jitter, uint64_t seed)
{
    mesh_buf m;
    rng_seed(seed);
    m.nv = (int64_t)(rings - 1) * segs + 2;
    m.nf = (int64_t)2 * segs * (rings - 1);
    m.v = malloc((size_t)m.nv * 3 * sizeof(double));
    m.f = malloc((size_t)m.nf * 3 * sizeof(int64_t));
    int64_t k = 0;
    m.v[0] = 0, m.v[1] = 0, m.v[2] = rad;
    k = 1;
    for (int i = 1; i < rings; ++i) {
        double th = PI * i / rings;
        for (int j = 0; j < segs; ++j) {
            double ph = 2 * PI * j / segs;
            double rr = rad * (1.0 + jitter * (rng_uniform() - 0.5));
            m.v[3 * k + 0] = rr * sin(th) * cos(ph);
            m.v[3 * k + 1] = rr * sin(th) * sin(ph);
            m.v[3 * k + 2] = rr * cos(th);
            ++k;
        }
    }
    m.v[3 * k + 0] = 0, m.v[3 * k + 1] = 0, m.v[3 * k + 2] = -rad;
    int64_t south = k, f = 0;
#define V(i, j) (1 + (int64_t)((i) - 1) * segs + ((j) % segs))
    for (int j = 0; j < segs; ++j) {
        m.f[3 * f + 0] = 0, m.f[3 * f + 1] = V(1, j), m.f[3 * f + 2] = V(1, j + 1), ++f;
        m.f[3 * f + 0] = south, m.f[3 * f + 1] = V(rings - 1, j + 1), m.f[3 * f + 2] = V(rings - 1, j), ++f;
    }
    for (int i = 1; i < rings - 1; ++i) {
        for (int j = 0; j < segs; ++j) {
            m.f[3 * f + 0] = V(i, j), m.f[3 * f + 1] = V(i + 1, j), m.f[3 * f + 2] = V(i + 1, j + 1), ++f;
            m.f[3 * f + 0] = V(i, j), m.f[3 * f + 1] = V(i + 1, j + 1), m.f[3 * f + 2] = V(i, j + 1), ++f;
        }
    }
#undef V
    m.nf = f;
    return m;
}

/* n random triangles of size `size` in the unit cube */
static mesh_buf random_soup(int64_t n, double size, uint64_t seed)
{
    mesh_buf m;
    rng_seed(seed);
    m.nv = 3 * n;
    m.nf = n;
    m.v = malloc((size_t)m.nv * 3 * sizeof(double));
    m.f = malloc((size_t)m.nf * 3 * sizeof(int64_t));
    for (int64_t t = 0; t < n; ++t) {
        double c[3] = {rng_uniform(), rng_uniform(), rng_uniform()};
        for (int k = 0; k < 3; ++k) {
            for (int i = 0; i < 3; ++i) {
                m.v[9 * t + 3 * k + i] = c[i] + size * (rng_uniform() - 0.5);
            }
            m.f[3 * t + k] = 3 * t + k;
        }
    }
    return m;
}

/* rays from a sphere around the box towards random points in it */
static void random_rays(int64_t n, const double lo[3], const double hi[3], uint64_t seed, double *o,
                        double *d)
{
    rng_seed(seed);
    double c[3], rad = 0;
    for (int i = 0; i < 3; ++i) {
        c[i] = 0.5 * (lo[i] + hi[i]);
        rad += (hi[i] - lo[i]) * (hi[i] - lo[i]);
    }
    rad = sqrt(rad);
    for (int64_t k = 0; k < n; ++k) {
        double z = 2 * rng_uniform() - 1, ph = 2 * PI * rng_uniform(), s = sqrt(1 - z * z);
        double p[3] = {s * cos(ph), s * sin(ph), z};
        double len = 0;
        for (int i = 0; i < 3; ++i) {
            /* a quarter of the rays start inside the box */
            o[3 * k + i] = (k % 4 == 0) ? lo[i] + (hi[i] - lo[i]) * rng_uniform() : c[i] + rad * p[i];
            double target = lo[i] + (hi[i] - lo[i]) * rng_uniform();
            d[3 * k + i] = target - o[3 * k + i];
            len += d[3 * k + i] * d[3 * k + i];
        }
        if (k % 4 == 0) { /* random direction from inside */
            double z2 = 2 * rng_uniform() - 1, ph2 = 2 * PI * rng_uniform(), s2 = sqrt(1 - z2 * z2);
            d[3 * k + 0] = s2 * cos(ph2), d[3 * k + 1] = s2 * sin(ph2), d[3 * k + 2] = z2;
        } else {
            for (int i = 0; i < 3; ++i) {
                d[3 * k + i] /= sqrt(len);
            }
        }
    }
}

/* The occupancy bits (gc_internal.h) say which records hold references or a subgrid, cell
 * for cell, and the last word's bits past the cells are clear; so are the bits of one layer of
 * the largest node (nx * ny cells) before the first cell and after the last, which the walk's
 * look-ahead may read. */
static void check_occupancy(const gc_grid *g, const char *label)
{
    int64_t bad = 0, occupied = 0;
    for (int64_t c = 0; c < g->n_cells; ++c) {
        const uint32_t want = g->cells[c].count != 0;
        bad += gc_occupied(g->occ, c) != want;
        occupied += want;
    }
    const uint64_t words = GC_OCC_WORDS(g->n_cells);
    const int64_t spare = (int64_t)(words * 64) - g->n_cells;
    const uint64_t past = spare ? g->occ[words - 1] >> (64 - spare) : 0;
    CHECK(bad == 0 && past == 0, "%s: %lld of %lld occupancy bits wrong (%lld occupied), bits past the cells %llx",
          label, (long long)bad, (long long)g->n_cells, (long long)occupied, (unsigned long long)past);
    int64_t layer = 1, outside = 0;
    for (int64_t k = 0; k < g->n_nodes; ++k) {
        const int64_t cells = (int64_t)g->nodes[k].n[0] * (int64_t)g->nodes[k].n[1];
        layer = cells > layer ? cells : layer;
    }
    for (int64_t c = 1; c <= layer; ++c) {
        outside += gc_occupied(g->occ, -c) + gc_occupied(g->occ, g->n_cells - 1 + c);
    }
    CHECK(outside == 0 && g->occ_pad * 64 >= layer,
          "%s: %lld occupancy bits set within a layer (%lld cells) outside the cells, pad %lld words", label,
          (long long)outside, (long long)layer, (long long)g->occ_pad);
}

/* Compare one grid with brute force on n rays; returns the number of disagreements. */
static int64_t compare_with_brute(const mesh_buf *mb, const gc_build_params *p, int64_t n,
                                  const double *o, const double *d, const char *label)
{
    char err[GC_ERROR_LEN] = "";
    gc_mesh mesh = as_mesh(mb);
    gc_grid *g = NULL;
    gc_status st = gc_grid_build(&mesh, p, &g, err);
    CHECK(st == GC_OK, "%s: build failed: %s", label, err);
    if (st != GC_OK) {
        return n;
    }
    check_occupancy(g, label);
    double *t = malloc((size_t)n * sizeof(double)), *tb = malloc((size_t)n * sizeof(double)),
           *tc = malloc((size_t)n * sizeof(double));
    int32_t *pr = malloc((size_t)n * sizeof(int32_t)), *pb = malloc((size_t)n * sizeof(int32_t)),
            *pc = malloc((size_t)n * sizeof(int32_t));
    uint32_t *steps = malloc((size_t)n * sizeof(uint32_t)), *tests = malloc((size_t)n * sizeof(uint32_t)),
             *subs = malloc((size_t)n * sizeof(uint32_t));
    CHECK(gc_count(g, n, o, d, tc, pc, steps, tests, subs, NULL, NULL, err) == GC_OK, "%s: count: %s", label, err);
    /* the timed twin on every sign stage this host runs, each equal to the
     * instrumented twin (SSE2) ray for ray; the host's best runs last and is
     * compared with brute force below */
    int64_t twin_bad = 0;
    const char *isas[3] = {"sse2", "avx2", "auto"};
    for (int i = 0; i < 3; ++i) {
        if (gc_traverse_set_isa(isas[i], err) != GC_OK) {
            continue; /* no AVX2 here, or a build without SSE2 */
        }
        CHECK(gc_intersect(g, n, o, d, t, pr, err) == GC_OK, "%s: intersect (%s): %s", label, isas[i], err);
        for (int64_t k = 0; k < n; ++k) {
            twin_bad += t[k] != tc[k] || pr[k] != pc[k];
        }
    }
    CHECK(gc_brute_force(&mesh, p->intersector, n, o, d, tb, pb, err) == GC_OK, "%s: brute: %s", label,
          err);
    int64_t bad = 0;
    for (int64_t k = 0; k < n; ++k) {
        int same = (t[k] == tb[k]) || (fabs(t[k] - tb[k]) <= 1e-9 * fabs(tb[k]));
        if (!same) {
            if (bad < 3) {
                fprintf(stderr, "  %s ray %lld: grid t=%.17g prim=%d, brute t=%.17g prim=%d\n", label,
                        (long long)k, t[k], pr[k], tb[k], pb[k]);
            }
            ++bad;
        }
    }
    CHECK(twin_bad == 0, "%s: timed and instrumented twins disagree on %lld rays", label,
          (long long)twin_bad);
    CHECK(bad == 0, "%s: %lld of %lld first hits differ from brute force", label, (long long)bad,
          (long long)n);
    free(t), free(tb), free(tc), free(pr), free(pb), free(pc), free(steps), free(tests), free(subs);
    gc_grid_free(g);
    return bad;
}

static void test_grids_match_brute_force(void)
{
    mesh_buf meshes[3] = {uv_sphere(24, 48, 0.5, 0.1, 1), random_soup(400, 0.08, 2),
                          random_soup(150, 0.6, 3)};
    const char *names[3] = {"sphere", "compact soup", "long soup"};
    const int64_t n = 2000;
    double *o = malloc((size_t)n * 3 * sizeof(double)), *d = malloc((size_t)n * 3 * sizeof(double));
    const int32_t resolutions[4][3] = {{1, 1, 1}, {3, 5, 2}, {16, 16, 16}, {40, 7, 23}};
    for (int mi = 0; mi < 3; ++mi) {
        double lo[3], hi[3];
        char err[GC_ERROR_LEN];
        gc_mesh mesh = as_mesh(&meshes[mi]);
        CHECK(gc_mesh_box(&mesh, lo, hi, err) == GC_OK, "box: %s", err);
        random_rays(n, lo, hi, 100 + (uint64_t)mi, o, d);
        for (int ri = 0; ri < 4; ++ri) {
            for (int isect = 0; isect < 2; ++isect) {
                for (int mail = 0; mail < 2; ++mail) {
                    for (int levels = 1; levels <= 3; ++levels) {
                        gc_build_params p = gc_build_params_default();
                        memcpy(p.resolution, resolutions[ri], sizeof p.resolution);
                        p.intersector = isect ? GC_WATERTIGHT : GC_MOLLER_TRUMBORE;
                        p.mailbox = mail;
                        p.levels = levels;
                        p.insertion = (ri == 1) ? GC_INSERT_BOUNDS : GC_INSERT_EXACT;
                        for (int lv = 1; lv < levels; ++lv) {
                            p.level_exponent[lv] = 3.0 / (2.0 * levels + 1 - 2.0 * lv);
                        }
                        char label[128];
                        snprintf(label, sizeof label, "%s res %dx%dx%d isect %d mail %d levels %d",
                                 names[mi], p.resolution[0], p.resolution[1], p.resolution[2], isect,
                                 mail, levels);
                        compare_with_brute(&meshes[mi], &p, n, o, d, label);
                    }
                }
            }
        }
    }
    free(o), free(d);
    for (int mi = 0; mi < 3; ++mi) {
        mesh_free(&meshes[mi]);
    }
}

/* Axis-parallel rays with +0 and -0 components, along cell faces, edges and corners. */
static void test_axis_parallel_and_cell_faces(void)
{
    mesh_buf m = random_soup(300, 0.1, 7);
    gc_mesh mesh = as_mesh(&m);
    double lo[3], hi[3];
    char err[GC_ERROR_LEN];
    CHECK(gc_mesh_box(&mesh, lo, hi, err) == GC_OK, "box: %s", err);
    const int res = 8;
    const int64_t n = 6 * 3 * (res + 1) * (res + 1);
    double *o = malloc((size_t)n * 3 * sizeof(double)), *d = malloc((size_t)n * 3 * sizeof(double));
    int64_t k = 0;
    for (int axis = 0; axis < 3; ++axis) {
        for (int sgn = 0; sgn < 2; ++sgn) {
            for (int zero_sign = 0; zero_sign < 3; ++zero_sign) {
                int a1 = (axis + 1) % 3, a2 = (axis + 2) % 3;
                for (int i = 0; i <= res; ++i) {
                    for (int j = 0; j <= res; ++j) {
                        double *oo = o + 3 * k, *dd = d + 3 * k;
                        /* on cell faces (i, j on the lattice), edges and corners */
                        oo[a1] = lo[a1] + (hi[a1] - lo[a1]) * i / res;
                        oo[a2] = lo[a2] + (hi[a2] - lo[a2]) * j / res;
                        oo[axis] = sgn ? hi[axis] + 1.0 : lo[axis] - 1.0;
                        dd[axis] = sgn ? -1.0 : 1.0;
                        dd[a1] = zero_sign == 1 ? -0.0 : 0.0;
                        dd[a2] = zero_sign == 2 ? -0.0 : 0.0;
                        ++k;
                    }
                }
            }
        }
    }
    for (int isect = 0; isect < 2; ++isect) {
        for (int levels = 1; levels <= 2; ++levels) {
            gc_build_params p = gc_build_params_default();
            p.resolution[0] = p.resolution[1] = p.resolution[2] = res;
            p.intersector = isect ? GC_WATERTIGHT : GC_MOLLER_TRUMBORE;
            p.levels = levels;
            p.level_exponent[1] = 1.0;
            compare_with_brute(&m, &p, k, o, d, "axis-parallel");
        }
    }
    free(o), free(d);
    mesh_free(&m);
}

/* pbrt's watertightness test: rays from inside a closed jittered mesh aimed
 * exactly at its vertices and at edge midpoints must all hit. */
static void test_watertight(void)
{
    mesh_buf m = uv_sphere(30, 60, 1.0, 0.2, 11);
    gc_mesh mesh = as_mesh(&m);
    const int64_t n = 20000;
    double *o = malloc((size_t)n * 3 * sizeof(double)), *d = malloc((size_t)n * 3 * sizeof(double));
    rng_seed(12);
    for (int64_t k = 0; k < n; ++k) {
        const int64_t f = (int64_t)(rng_uniform() * (double)m.nf) % m.nf;
        const double *a = m.v + 3 * m.f[3 * f], *b = m.v + 3 * m.f[3 * f + 1];
        double target[3];
        for (int i = 0; i < 3; ++i) {
            o[3 * k + i] = 0.3 * (rng_uniform() - 0.5);
            target[i] = (k % 2 == 0) ? a[i] : 0.5 * (a[i] + b[i]);
            d[3 * k + i] = target[i] - o[3 * k + i];
        }
    }
    gc_build_params p = gc_build_params_default();
    p.resolution[0] = p.resolution[1] = p.resolution[2] = 12;
    char err[GC_ERROR_LEN];
    int64_t leaks[2] = {0, 0};
    for (int isect = 0; isect < 2; ++isect) {
        p.intersector = isect ? GC_WATERTIGHT : GC_MOLLER_TRUMBORE;
        gc_grid *g = NULL;
        CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_OK, "watertight build: %s", err);
        double *t = malloc((size_t)n * sizeof(double));
        int32_t *pr = malloc((size_t)n * sizeof(int32_t));
        CHECK(gc_intersect(g, n, o, d, t, pr, err) == GC_OK, "watertight: %s", err);
        for (int64_t k = 0; k < n; ++k) {
            leaks[isect] += pr[k] < 0;
        }
        free(t), free(pr);
        gc_grid_free(g);
    }
    CHECK(leaks[1] == 0, "watertight intersector leaked %lld of %lld rays", (long long)leaks[1],
          (long long)n);
    printf("watertightness: %lld rays at vertices and edges: watertight leaks %lld, "
           "Moller-Trumbore leaks %lld\n",
           (long long)n, (long long)leaks[1], (long long)leaks[0]);
    free(o), free(d);
    mesh_free(&m);
}

/* The instruction-set switch: names it does not know are refused with a
 * message, and "auto" restores the host's best. */
static void test_isa_switch(void)
{
    char err[GC_ERROR_LEN] = "";
    const char *best = gc_traverse_isa();
    CHECK(!strcmp(best, "avx2") || !strcmp(best, "sse2") || !strcmp(best, "scalar"), "unknown isa %s", best);
    CHECK(gc_traverse_set_isa("avx512", err) == GC_ERR_ARGUMENT && strstr(err, "avx512"),
          "an unknown instruction set is refused with its name: %s", err);
    CHECK(gc_traverse_set_isa(NULL, err) == GC_ERR_ARGUMENT, "a missing name is refused");
    if (gc_traverse_set_isa("sse2", err) == GC_OK) {
        CHECK(!strcmp(gc_traverse_isa(), "sse2"), "sse2 forced, %s reported", gc_traverse_isa());
    }
    CHECK(gc_traverse_set_isa("auto", err) == GC_OK, "auto: %s", err);
    CHECK(!strcmp(gc_traverse_isa(), best), "auto gives %s back, not %s", best, gc_traverse_isa());
    printf("timed twin's sign stage on this host: %s\n", best);
}

static void test_refusals(void)
{
    mesh_buf m = random_soup(10, 0.2, 5);
    gc_mesh mesh = as_mesh(&m);
    char err[GC_ERROR_LEN];
    gc_grid *g = (gc_grid *)&err; /* must be reset to NULL on failure */
    gc_build_params p = gc_build_params_default();

    p.resolution[0] = 65536, p.resolution[1] = 65536, p.resolution[2] = 2;
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_OVERFLOW && g == NULL && strstr(err, "overflow"),
          "32-bit overflow not refused: %s", err);

    p.resolution[0] = 2000, p.resolution[1] = 2000, p.resolution[2] = 500;
    p.memory_limit_bytes = (uint64_t)64 << 20;
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_MEMORY_LIMIT && g == NULL &&
              strstr(err, "memory limit"),
          "memory limit not refused: %s", err);

    p = gc_build_params_default();
    p.resolution[1] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT, "zero resolution not refused");

    p = gc_build_params_default();
    m.f[4] = m.nv; /* out of range */
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && strstr(err, "outside"),
          "out-of-range index not refused: %s", err);
    m.f[4] = -1;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT, "negative index not refused");
    m.f[4] = 4;
    m.v[5] = NAN;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && strstr(err, "finite"),
          "NaN vertex not refused: %s", err);
    m.v[5] = 0.5;

    /* vertices near +-DBL_MAX: the box's extent overflows to inf (found by fuzzing: a segfault) */
    {
        const double v0 = m.v[0], v3 = m.v[3];
        const int64_t keep[3] = {m.f[0], m.f[1], m.f[2]};
        m.v[0] = -1.7e308, m.v[3] = 1.7e308;
        m.f[0] = 0, m.f[1] = 1, m.f[2] = 1;
        err[0] = 0;
        CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && g == NULL && strstr(err, "too wide"),
              "a box whose extent overflows not refused: %s", err);
        p.has_box = 1;
        for (int i = 0; i < 3; ++i) {
            p.box_lo[i] = -1.7e308, p.box_hi[i] = 1.7e308;
        }
        err[0] = 0;
        CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && g == NULL && strstr(err, "too wide"),
              "a given box whose extent overflows not refused: %s", err);
        p = gc_build_params_default();
        m.v[0] = v0, m.v[3] = v3;
        m.f[0] = keep[0], m.f[1] = keep[1], m.f[2] = keep[2];
    }

    gc_mesh empty = {m.v, m.nv, m.f, 0};
    CHECK(gc_grid_build(&empty, &p, &g, err) == GC_ERR_ARGUMENT, "empty mesh without a box accepted");
    p.has_box = 1;
    for (int i = 0; i < 3; ++i) {
        p.box_lo[i] = 0.0, p.box_hi[i] = 1.0;
    }
    p.resolution[0] = p.resolution[1] = p.resolution[2] = 4;
    CHECK(gc_grid_build(&empty, &p, &g, err) == GC_OK, "empty grid with a box refused: %s", err);
    double o[3] = {-1, 0.5, 0.5}, d[3] = {1, 0, 0}, t;
    int32_t pr;
    uint32_t steps;
    CHECK(gc_count(g, 1, o, d, &t, &pr, &steps, NULL, NULL, NULL, NULL, err) == GC_OK && pr == -1 && steps == 4,
          "empty grid: ray along x should visit 4 cells, visited %u", steps);
    d[0] = 0;
    CHECK(gc_intersect(g, 1, o, d, &t, &pr, err) == GC_ERR_ARGUMENT, "zero direction accepted");
    d[0] = NAN;
    CHECK(gc_intersect(g, 1, o, d, &t, &pr, err) == GC_ERR_ARGUMENT, "NaN direction accepted");
    gc_grid_free(g);
    mesh_free(&m);
}

/* The memory limit counts the packs once: a 2x2x2 grid over a sphere, whose
 * references outweigh everything else, builds under a limit of 100 bytes a
 * reference (the packs take 76, the references 4) and is refused under 40. */
static void test_memory_limit_counts_packs_once(void)
{
    mesh_buf m = uv_sphere(100, 200, 1.0, 0.0, 7);
    gc_mesh mesh = as_mesh(&m);
    char err[GC_ERROR_LEN];
    gc_grid *g = NULL;
    gc_build_params p = gc_build_params_default();
    p.resolution[0] = p.resolution[1] = p.resolution[2] = 2;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_OK, "2x2x2 sphere grid refused: %s", err);
    gc_grid_info info;
    gc_grid_get_info(g, &info);
    const uint64_t n = (uint64_t)info.n_refs;
    gc_grid_free(g);
    g = NULL;
    p.memory_limit_bytes = 100 * n + ((uint64_t)64 << 10);
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_OK,
          "%llu references refused under 100 bytes a reference: %s", (unsigned long long)n, err);
    gc_grid_free(g);
    g = (gc_grid *)&err;
    p.memory_limit_bytes = 40 * n;
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_MEMORY_LIMIT && g == NULL && strstr(err, "memory limit"),
          "%llu references accepted under 40 bytes a reference: %s", (unsigned long long)n, err);
    mesh_free(&m);
}

/* Scaled scenes: hits scale exactly with the scene. */
static void test_scaled_scenes(void)
{
    const double scales[3] = {1e-20, 1.0, 1e20};
    const int64_t n = 500;
    for (int si = 0; si < 3; ++si) {
        mesh_buf m = uv_sphere(12, 24, 0.5, 0.1, 21);
        for (int64_t k = 0; k < 3 * m.nv; ++k) {
            m.v[k] *= scales[si];
        }
        gc_mesh mesh = as_mesh(&m);
        double lo[3], hi[3];
        char err[GC_ERROR_LEN];
        CHECK(gc_mesh_box(&mesh, lo, hi, err) == GC_OK, "box: %s", err);
        double *o = malloc((size_t)n * 3 * sizeof(double)), *d = malloc((size_t)n * 3 * sizeof(double));
        random_rays(n, lo, hi, 22, o, d);
        for (int isect = 0; isect < 2; ++isect) {
            gc_build_params p = gc_build_params_default();
            p.resolution[0] = p.resolution[1] = p.resolution[2] = 9;
            p.intersector = isect ? GC_WATERTIGHT : GC_MOLLER_TRUMBORE;
            char label[64];
            snprintf(label, sizeof label, "scaled %g", scales[si]);
            compare_with_brute(&m, &p, n, o, d, label);
        }
        free(o), free(d);
        mesh_free(&m);
    }
}


/* The unit cube as 12 triangles over 8 shared corners (outward, counter-clockwise). */
static const double CUBE_V[8][3] = {{0, 0, 0}, {1, 0, 0}, {1, 1, 0}, {0, 1, 0},
                                    {0, 0, 1}, {1, 0, 1}, {1, 1, 1}, {0, 1, 1}};
static const int64_t CUBE_F[12][3] = {{0, 2, 1}, {0, 3, 2}, {4, 5, 6}, {4, 6, 7}, {0, 1, 5}, {0, 5, 4},
                                      {1, 2, 6}, {1, 6, 5}, {2, 3, 7}, {2, 7, 6}, {3, 0, 4}, {3, 4, 7}};

static int cube_watertight(const double *v, int64_t nv, const int64_t *f, int64_t nf)
{
    gc_mesh mesh = {v, nv, f, nf};
    int wt = -1;
    char err[GC_ERROR_LEN];
    CHECK(gc_mesh_watertight(&mesh, &wt, err) == GC_OK, "watertight: %s", err);
    return wt;
}

/* The cube with split vertices: every face its own three corners (36 vertices, 8 positions). */
static void split_cube(double v[36][3], int64_t f[12][3])
{
    for (int t = 0; t < 12; ++t) {
        for (int k = 0; k < 3; ++k) {
            memcpy(v[3 * t + k], CUBE_V[CUBE_F[t][k]], sizeof v[0]);
            f[t][k] = 3 * t + k;
        }
    }
}

/* Scene sums of the unit cube, known in closed form; watertightness of its variants. */
static void test_mesh_sums(void)
{
    gc_mesh mesh = {&CUBE_V[0][0], 8, &CUBE_F[0][0], 12};
    gc_mesh_sums s;
    double ar[12];
    int64_t n_ar = -1;
    char err[GC_ERROR_LEN];
    CHECK(gc_mesh_sums_compute(&mesh, 5, ar, &n_ar, &s, err) == GC_OK, "sums: %s", err);
    for (int a = 0; a < 3; ++a) {
        /* 8 of the 12 triangles span each axis; 4 project with area 1/2 along it; every
         * triangle not perpendicular to the axis projects legs 1, 1 and diagonal 1 or sqrt 2. */
        CHECK(s.box_lo[a] == 0.0 && s.box_hi[a] == 1.0, "cube box axis %d", a);
        CHECK(s.e1[a] == 8.0, "cube e1[%d] = %g, want 8", a, s.e1[a]);
        CHECK(s.e2[a] == 2.0, "cube e2[%d] = %g, want 2", a, s.e2[a]);
        CHECK(s.pair[a] == 4.0, "cube pair[%d] = %g, want 4", a, s.pair[a]);
    }
    /* along an axis: 4 perpendicular triangles keep their full perimeter 2 + sqrt 2; the 8
     * others project to segments: legs 1 and 0 and diagonal 1 -> 2 (counted twice). */
    double want_per = 4.0 * (2.0 + sqrt(2.0)) + 8.0 * 2.0;
    CHECK(fabs(s.perimeters[0] - want_per) < 1e-12, "cube perimeter %.17g, want %.17g", s.perimeters[0],
          want_per);
    CHECK(s.triple == 0.0 && s.area == 6.0 && s.n_good == 12, "cube triple %g area %g good %lld", s.triple,
          s.area, (long long)s.n_good);
    CHECK(fabs(s.vol6 - 6.0) < 1e-15, "cube 6 x volume = %.17g, want 6", s.vol6);
    CHECK(n_ar == 3 && ar[0] == 2.0 && ar[1] == 2.0 && ar[2] == 2.0, "cube aspect sample: %lld values",
          (long long)n_ar); /* triangles 0, 5, 10: right isosceles, AR = 2 */

    CHECK(cube_watertight(&CUBE_V[0][0], 8, &CUBE_F[0][0], 12) == 1, "closed cube not watertight");
    CHECK(cube_watertight(&CUBE_V[0][0], 8, &CUBE_F[0][0], 10) == 0, "open cube called watertight");
    int64_t twice[24][3];
    memcpy(twice, CUBE_F, sizeof CUBE_F);
    memcpy(twice[12], CUBE_F, sizeof CUBE_F);
    CHECK(cube_watertight(&CUBE_V[0][0], 8, &twice[0][0], 24) == 0, "doubled cube (4 faces/edge) watertight");
    /* split vertices: every face gets its own three corners, one of them at -0.0 */
    double split[36][3];
    int64_t sf[12][3];
    split_cube(split, sf);
    split[0][0] = -0.0;
    CHECK(cube_watertight(&split[0][0], 36, &sf[0][0], 12) == 1, "split-vertex cube not watertight");
    split[0][0] = 1e-300;
    CHECK(cube_watertight(&split[0][0], 36, &sf[0][0], 12) == 0, "moved corner still watertight");
    int64_t bad[3] = {0, 1, 8};
    gc_mesh bm = {&CUBE_V[0][0], 8, bad, 1};
    int wt;
    CHECK(gc_mesh_watertight(&bm, &wt, err) == GC_ERR_ARGUMENT && strstr(err, "out of range"),
          "out-of-range index accepted");
    CHECK(gc_mesh_sums_compute(&bm, 1, NULL, NULL, &s, err) == GC_ERR_ARGUMENT,
          "out-of-range index accepted by the sums");
    /* beyond 32-bit vertex ids: refused before anything is read */
    gc_mesh huge = {&CUBE_V[0][0], (int64_t)UINT32_MAX, &CUBE_F[0][0], 12};
    CHECK(gc_mesh_watertight(&huge, &wt, err) == GC_ERR_ARGUMENT && strstr(err, "too large"),
          "2^32 - 1 vertices accepted by the watertightness test");
}

/* The build's prepared triangle/box test (overlap.h) against the plain one
 * (gc_triangle_box_overlap) on seeded random triangles and boxes of mixed sizes,
 * near the origin and far from it, including triangles thin along two axes
 * (the rows the build fills without a test). */
static void test_prepared_overlap(void)
{
    int64_t differ = 0, overlaps = 0;
    const int64_t n = 200000;
    for (int64_t k = 0; k < n; ++k) {
        rng_seed(9000 + (uint64_t)k);
        const double shift = (k % 3 == 0) ? 1e6 : 0.0;
        const double size = pow(10.0, -3.0 * rng_uniform());
        double v[3][3], lo[3], hi[3], thin[3] = {1.0, 1.0, 1.0};
        if (k % 4 == 1) { /* a sliver along one axis */
            const int a = (int)(k / 4 % 3);
            thin[(a + 1) % 3] = thin[(a + 2) % 3] = 1e-3;
        }
        for (int j = 0; j < 3; ++j) {
            for (int i = 0; i < 3; ++i) {
                v[j][i] = shift + size * thin[i] * (2.0 * rng_uniform() - 1.0);
            }
        }
        for (int i = 0; i < 3; ++i) {
            const double c = shift + size * (2.0 * rng_uniform() - 1.0), h = size * rng_uniform();
            lo[i] = c - h;
            hi[i] = c + h;
        }
        gc_tri_box_prep p;
        gc_tri_box_prepare(&p, v[0], v[1], v[2]);
        const int a = gc_triangle_box_overlap(v[0], v[1], v[2], lo, hi);
        const int b = gc_tri_box_prepared_overlap(&p, lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], 0.5 * (lo[0] + hi[0]),
                                                  0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2]), 0.5 * (hi[0] - lo[0]),
                                                  0.5 * (hi[1] - lo[1]), 0.5 * (hi[2] - lo[2]));
        differ += a != b;
        overlaps += a;
    }
    CHECK(differ == 0, "prepared triangle/box test differs from the plain one on %lld of %lld cases",
          (long long)differ, (long long)n);
    CHECK(overlaps > n / 10 && overlaps < n - n / 10, "overlap cases not mixed: %lld of %lld overlap",
          (long long)overlaps, (long long)n);

    /* a triangle within the box's slab along one axis: the 2D test agrees with the 3D one */
    differ = overlaps = 0;
    for (int64_t k = 0; k < n; ++k) {
        rng_seed(19000 + (uint64_t)k);
        const int a = (int)(k % 3);
        const double shift = (k % 5 == 0) ? 1e6 : 0.0;
        const double size = pow(10.0, -3.0 * rng_uniform());
        double v[3][3], lo[3], hi[3], m[3], h[3];
        for (int i = 0; i < 3; ++i) {
            const double c = shift + size * (2.0 * rng_uniform() - 1.0), hh = size * rng_uniform();
            lo[i] = c - hh;
            hi[i] = c + hh;
            m[i] = 0.5 * (lo[i] + hi[i]);
            h[i] = 0.5 * (hi[i] - lo[i]);
        }
        for (int j = 0; j < 3; ++j) {
            for (int i = 0; i < 3; ++i) {
                v[j][i] = i == a ? lo[i] + (hi[i] - lo[i]) * rng_uniform()
                                 : shift + size * (2.0 * rng_uniform() - 1.0);
            }
            if (k % 7 == 3) { /* a vertex on the slab's face */
                v[j][a] = (j == 0) ? lo[a] : v[j][a];
            }
        }
        gc_tri_slab_prep sp;
        gc_tri_slab_prepare(&sp, v[0], v[1], v[2], a);
        const int want = gc_triangle_box_overlap(v[0], v[1], v[2], lo, hi);
        differ += gc_tri_slab_prepared_overlap(&sp, lo[0], lo[1], lo[2], hi[0], hi[1], hi[2], m[0], m[1], m[2], h[0],
                                               h[1], h[2]) != want;
        overlaps += want;
    }
    CHECK(differ == 0, "2D slab triangle/box test differs from the 3D one on %lld of %lld cases",
          (long long)differ, (long long)n);
    CHECK(overlaps > n / 10 && overlaps < n - n / 10, "slab overlap cases not mixed: %lld of %lld overlap",
          (long long)overlaps, (long long)n);
}

/* The same grid, byte for byte, for any number of build threads: uniform and
 * nested, exact and bounds insertion, a compact soup, a long soup (whose pair
 * buffers grow inside the parts) and a sphere, each large enough for several
 * parts.  Also: a negative thread count is refused. */
static int grids_identical(const gc_grid *a, const gc_grid *b)
{
    return a->n_tris == b->n_tris && a->n_nodes == b->n_nodes && a->n_cells == b->n_cells &&
           a->n_refs == b->n_refs && a->levels == b->levels &&
           !memcmp(a->nodes, b->nodes, (size_t)a->n_nodes * sizeof(gc_node)) &&
           !memcmp(a->cells, b->cells, (size_t)a->n_cells * sizeof(gc_cell)) &&
           !memcmp(a->ref_tris, b->ref_tris, (size_t)GC_PACK_BYTES(a->n_refs));
}

static void test_threads_same_grid(void)
{
    mesh_buf meshes[3] = {random_soup(70001, 0.02, 21), random_soup(40000, 0.3, 22),
                          uv_sphere(160, 240, 0.5, 0.05, 23)};
    const char *names[3] = {"compact soup", "long soup", "sphere"};
    char err[GC_ERROR_LEN];
    for (int mi = 0; mi < 3; ++mi) {
        gc_mesh mesh = as_mesh(&meshes[mi]);
        for (int variant = 0; variant < 3; ++variant) {
            gc_build_params p = gc_build_params_default();
            p.resolution[0] = 37, p.resolution[1] = 41, p.resolution[2] = 29;
            p.insertion = variant == 1 ? GC_INSERT_BOUNDS : GC_INSERT_EXACT;
            p.levels = variant == 2 ? 2 : 1;
            p.level_exponent[1] = 3.0 / 3.0;
            gc_grid *one = NULL;
            p.threads = 1;
            CHECK(gc_grid_build(&mesh, &p, &one, err) == GC_OK, "%s: one thread: %s", names[mi], err);
            for (int threads = 2; threads <= 5 && one; threads += 3) {
                gc_grid *many = NULL;
                p.threads = threads;
                CHECK(gc_grid_build(&mesh, &p, &many, err) == GC_OK, "%s: %d threads: %s", names[mi],
                      threads, err);
                CHECK(many && grids_identical(one, many), "%s variant %d: %d threads built another grid",
                      names[mi], variant, threads);
                gc_grid_free(many);
            }
            gc_grid_free(one);
        }
        /* a bad index in a later part is named as one thread names it */
        const int64_t bad_face = meshes[mi].nf - 7, keep = meshes[mi].f[3 * bad_face + 1];
        meshes[mi].f[3 * bad_face + 1] = meshes[mi].nv + 3;
        char expect[GC_ERROR_LEN], got[GC_ERROR_LEN];
        gc_build_params p = gc_build_params_default();
        gc_grid *g = NULL;
        double blo[3], bhi[3];
        CHECK(gc_mesh_box(&mesh, blo, bhi, expect) == GC_ERR_ARGUMENT,
              "%s: gc_mesh_box accepted a bad index", names[mi]);
        p.threads = 2;
        CHECK(gc_grid_build(&mesh, &p, &g, got) == GC_ERR_ARGUMENT && g == NULL && !strcmp(got, expect),
              "%s: a bad index in the second part: '%s', not '%s'", names[mi], got, expect);
        meshes[mi].f[3 * bad_face + 1] = keep;
    }
    gc_build_params p = gc_build_params_default();
    gc_mesh mesh = as_mesh(&meshes[0]);
    gc_grid *g = (gc_grid *)&err;
    p.threads = -1;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && g == NULL && strstr(err, "threads"),
          "negative threads not refused: %s", err);
    for (int mi = 0; mi < 3; ++mi) {
        mesh_free(&meshes[mi]);
    }
}

/* The faces of cell c of a uniform grid, in reference order, into out (room for its count). */
static uint32_t cell_faces(const gc_grid *g, int64_t c, int32_t *out)
{
    const gc_cell cell = g->cells[c];
    for (uint32_t k = 0; k < cell.count; ++k) {
        const uint32_t r = cell.begin + k;
        out[k] = g->ref_tris[r / GC_LANES].id[r % GC_LANES];
    }
    return cell.count;
}

static int cmp_i32(const void *a, const void *b)
{
    const int32_t x = *(const int32_t *)a, y = *(const int32_t *)b;
    return (x > y) - (x < y);
}

/* The face order the build reads, on a UV sphere of the given size written ring by
 * ring (consecutive faces are neighbours) and on the same faces shuffled: the
 * sphere keeps its order, so each cell lists its faces by index; the shuffled faces
 * are put in Morton order when `sorted` (a mesh past SORT_MIN_BYTES) and keep
 * theirs otherwise.  Either way each cell holds the same faces, and first hits
 * agree with brute force on n_rays rays. */
static void check_face_order(int rings, int segs, int sorted, int64_t n_rays, uint64_t seed)
{
    mesh_buf m = uv_sphere(rings, segs, 0.5, 0.05, seed);
    mesh_buf s = m; /* the faces shuffled: s.f[t] = m.f[perm[t]] */
    s.f = malloc((size_t)m.nf * 3 * sizeof(int64_t));
    int32_t *perm = malloc((size_t)m.nf * sizeof(int32_t));
    for (int64_t t = 0; t < m.nf; ++t) {
        perm[t] = (int32_t)t;
    }
    rng_seed(seed + 1);
    for (int64_t t = m.nf - 1; t > 0; --t) {
        const int64_t u = (int64_t)(rng_uniform() * (double)(t + 1));
        const int32_t x = perm[t];
        perm[t] = perm[u], perm[u] = x;
    }
    for (int64_t t = 0; t < m.nf; ++t) {
        memcpy(s.f + 3 * t, m.f + 3 * (int64_t)perm[t], 3 * sizeof(int64_t));
    }
    gc_build_params p = gc_build_params_default();
    p.resolution[0] = 23, p.resolution[1] = 19, p.resolution[2] = 21;
    p.threads = 2;
    gc_mesh mm = as_mesh(&m), ms = as_mesh(&s);
    gc_grid *gm = NULL, *gs = NULL;
    char err[GC_ERROR_LEN];
    CHECK(gc_grid_build(&mm, &p, &gm, err) == GC_OK, "sphere %dx%d: %s", rings, segs, err);
    CHECK(gc_grid_build(&ms, &p, &gs, err) == GC_OK, "shuffled sphere %dx%d: %s", rings, segs, err);
    if (gm && gs) {
        int32_t *a = malloc((size_t)m.nf * sizeof(int32_t)), *b = malloc((size_t)m.nf * sizeof(int32_t));
        int64_t unordered_m = 0, unordered_s = 0, differ = 0, refs = 0;
        for (int64_t c = 0; c < (int64_t)p.resolution[0] * p.resolution[1] * p.resolution[2]; ++c) {
            const uint32_t na = cell_faces(gm, c, a), nb = cell_faces(gs, c, b);
            int out_m = 0, out_s = 0;
            for (uint32_t k = 1; k < na; ++k) {
                out_m |= a[k] <= a[k - 1];
            }
            for (uint32_t k = 1; k < nb; ++k) {
                out_s |= b[k] <= b[k - 1];
            }
            for (uint32_t k = 0; k < nb; ++k) {
                b[k] = perm[b[k]]; /* the shuffled mesh's face b[k] is the sphere's perm[b[k]] */
            }
            unordered_m += out_m;
            unordered_s += out_s;
            qsort(a, na, sizeof *a, cmp_i32);
            qsort(b, nb, sizeof *b, cmp_i32);
            differ += na != nb || (na > 0 && memcmp(a, b, na * sizeof *a) != 0);
            refs += na;
        }
        CHECK(refs > m.nf && differ == 0,
              "sphere %dx%d: shuffling the faces changed %lld cells' faces (%lld references)", rings, segs,
              (long long)differ, (long long)refs);
        CHECK(unordered_m == 0, "sphere %dx%d: its order was not kept: %lld cells list faces out of order",
              rings, segs, (long long)unordered_m);
        CHECK(sorted ? unordered_s > 0 : unordered_s == 0,
              sorted ? "sphere %dx%d: the shuffled faces were not reordered (%lld cells out of order)"
                     : "sphere %dx%d: the shuffled faces were reordered (%lld cells out of order)",
              rings, segs, (long long)unordered_s);
        free(a), free(b);
    }
    gc_grid_free(gm), gc_grid_free(gs);
    double *o = malloc((size_t)n_rays * 3 * sizeof(double)), *d = malloc((size_t)n_rays * 3 * sizeof(double));
    double lo[3], hi[3];
    CHECK(gc_mesh_box(&mm, lo, hi, err) == GC_OK, "box: %s", err);
    random_rays(n_rays, lo, hi, seed + 2, o, d);
    compare_with_brute(&m, &p, n_rays, o, d, "sphere in its own face order");
    compare_with_brute(&s, &p, n_rays, o, d, "sphere with shuffled faces");
    /* a bad index in faces 0 and 1 (the first pair sampled, where the mesh is sampled) is refused as
     * the face pass refuses it */
    const int64_t keep = s.f[4];
    s.f[4] = s.nv + 5;
    gc_grid *bad = NULL;
    CHECK(gc_grid_build(&ms, &p, &bad, err) == GC_ERR_ARGUMENT && bad == NULL && strstr(err, "face 1 refers to vertex"),
          "sphere %dx%d: a bad index in a sampled face: %s", rings, segs, err);
    s.f[4] = keep;
    free(o), free(d), free(perm), free(s.f);
    mesh_free(&m);
}

/* 42,960 faces (1.5 MB with the vertices): no sort; 502,800 (18 MB): the shuffled
 * faces sorted. */
static void test_face_order(void)
{
    check_face_order(120, 180, 0, 2000, 41);
    check_face_order(420, 600, 1, 100, 44);
}

/* Vertices no face uses are ignored, even a NaN or a far one (the build's
 * Morton codes are taken over the box of every finite vertex). */
static void test_unused_vertices(void)
{
    mesh_buf m = random_soup(300, 0.1, 31);
    mesh_buf x = m;
    x.nv = m.nv + 2;
    x.v = malloc((size_t)x.nv * 3 * sizeof(double));
    memcpy(x.v, m.v, (size_t)m.nv * 3 * sizeof(double));
    for (int i = 0; i < 3; ++i) {
        x.v[3 * m.nv + i] = NAN;
        x.v[3 * m.nv + 3 + i] = 1e30;
    }
    const int64_t n = 1000;
    double *o = malloc((size_t)n * 3 * sizeof(double)), *d = malloc((size_t)n * 3 * sizeof(double));
    double lo[3], hi[3];
    char err[GC_ERROR_LEN];
    gc_mesh mesh = as_mesh(&x);
    CHECK(gc_mesh_box(&mesh, lo, hi, err) == GC_OK && hi[0] < 2.0, "unused vertices changed the box: %s",
          err);
    random_rays(n, lo, hi, 32, o, d);
    gc_build_params p = gc_build_params_default();
    p.resolution[0] = p.resolution[1] = p.resolution[2] = 9;
    compare_with_brute(&x, &p, n, o, d, "unused NaN and far vertices");
    free(o), free(d), free(x.v);
    mesh_free(&m);
}

/* Occupied cells entered: two small triangles in cells 0 and 2 of a 4x1x1 grid
 * over [0,4]x[0,1]x[0,1], each in the plane x = cell + 0.5 over y, z in [0.1, 0.3].
 * A ray along x that misses them steps 4 cells and enters the 2 occupied ones; one
 * that hits the first stops in cell 0, having entered 1.  Occupancy changes: 3 for
 * the first (occupied, empty, occupied, empty), 0 for the second, 4 for a ray along
 * -x that misses (its first cell empty after the "occupied" before it).  The unit cube's 12
 * triangles over 8 corners have 8 distinct positions, and so have its 36 corners
 * given one by one. */
static void test_visits_and_positions(void)
{
    const double v[6][3] = {{0.5, 0.1, 0.1}, {0.5, 0.3, 0.1}, {0.5, 0.1, 0.3},
                            {2.5, 0.1, 0.1}, {2.5, 0.3, 0.1}, {2.5, 0.1, 0.3}};
    const int64_t f[2][3] = {{0, 1, 2}, {3, 4, 5}};
    gc_mesh mesh = {&v[0][0], 6, &f[0][0], 2};
    gc_build_params p = gc_build_params_default();
    p.has_box = 1;
    p.box_lo[0] = p.box_lo[1] = p.box_lo[2] = 0.0;
    p.box_hi[0] = 4.0, p.box_hi[1] = p.box_hi[2] = 1.0;
    p.resolution[0] = 4, p.resolution[1] = p.resolution[2] = 1;
    gc_grid *g = NULL;
    char err[GC_ERROR_LEN] = "";
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_OK, "visits grid: %s", err);
    if (!g) {
        return;
    }
    const double o[3][3] = {{-1.0, 0.8, 0.8}, {-1.0, 0.15, 0.15}, {5.0, 0.8, 0.8}};
    const double d[3][3] = {{1, 0, 0}, {1, 0, 0}, {-1, 0, 0}};
    uint32_t steps[3] = {0, 0, 0}, visits[3] = {9, 9, 9}, changes[3] = {9, 9, 9};
    CHECK(gc_count(g, 3, &o[0][0], &d[0][0], NULL, NULL, steps, NULL, NULL, visits, changes, err) == GC_OK,
          "count: %s", err);
    /* cells occupied, empty, occupied, empty along +x; the cell before the first counts as occupied */
    CHECK(steps[0] == 4 && visits[0] == 2 && changes[0] == 3,
          "a missing ray: %u steps, %u visits and %u changes, want 4, 2 and 3", steps[0], visits[0], changes[0]);
    CHECK(steps[1] == 1 && visits[1] == 1 && changes[1] == 0,
          "a hitting ray: %u steps, %u visits and %u changes, want 1, 1 and 0", steps[1], visits[1], changes[1]);
    CHECK(steps[2] == 4 && visits[2] == 2 && changes[2] == 4,
          "a missing ray along -x: %u steps, %u visits and %u changes, want 4, 2 and 4", steps[2], visits[2],
          changes[2]);
    gc_grid_free(g);

    int wt = -1;
    int64_t positions = -1;
    gc_mesh cube = {&CUBE_V[0][0], 8, &CUBE_F[0][0], 12};
    CHECK(gc_mesh_topology(&cube, &wt, &positions, err) == GC_OK && wt == 1 && positions == 8,
          "cube: watertight %d with %lld positions, want 1 and 8", wt, (long long)positions);
    double split_v[36][3];
    int64_t split_f[12][3];
    split_cube(split_v, split_f);
    gc_mesh split = {&split_v[0][0], 36, &split_f[0][0], 12};
    CHECK(gc_mesh_topology(&split, &wt, &positions, err) == GC_OK && wt == 1 && positions == 8,
          "split cube: watertight %d with %lld positions, want 1 and 8", wt, (long long)positions);
    split_v[0][0] = 0.25; /* one corner moved: a ninth position, and a crack */
    CHECK(gc_mesh_topology(&split, &wt, &positions, err) == GC_OK && wt == 0 && positions == 9,
          "cracked cube: watertight %d with %lld positions, want 0 and 9", wt, (long long)positions);
}

/* The large arrays' allocations: zeroed, mapped on their own and aligned to a
 * huge page from one huge page on (Linux), contents kept by a move; and a grid
 * whose packs and cells both pass that size still meets brute force. */
static void test_big_arrays(void)
{
    const size_t sizes[5] = {1, 4096, GC_HUGE_PAGE_BYTES - 1, GC_HUGE_PAGE_BYTES, 3 * GC_HUGE_PAGE_BYTES + 12345};
    for (int i = 0; i < 5; ++i) {
        const size_t n = sizes[i];
        size_t mapped = 1;
        unsigned char *p = gc_big_alloc(n, &mapped);
        CHECK(p != NULL, "gc_big_alloc(%zu) failed", n);
        if (!p) {
            continue;
        }
        size_t nonzero = 0;
        for (size_t k = 0; k < n; ++k) {
            nonzero += p[k] != 0;
        }
        CHECK(nonzero == 0, "gc_big_alloc(%zu): %zu bytes not zero", n, nonzero);
        CHECK(n >= GC_HUGE_PAGE_BYTES ? mapped == 0 || (mapped >= n && mapped % GC_HUGE_PAGE_BYTES == 0)
                                      : mapped == 0,
              "gc_big_alloc(%zu) mapped %zu bytes", n, mapped);
#if defined(__linux__)
        CHECK(n < GC_HUGE_PAGE_BYTES || (mapped && (uintptr_t)p % GC_HUGE_PAGE_BYTES == 0),
              "gc_big_alloc(%zu) not mapped on a huge page boundary", n);
#endif
        memset(p, 0xab, n); /* every byte writable */
        gc_big_free(p, mapped);
        unsigned char *q = malloc(n);
        CHECK(q != NULL, "malloc(%zu) failed", n);
        if (!q) {
            continue;
        }
        for (size_t k = 0; k < n; ++k) {
            q[k] = (unsigned char)(k * 131u + 7u);
        }
        unsigned char *r = gc_big_move(q, n, &mapped);
        size_t changed = 0;
        for (size_t k = 0; k < n; ++k) {
            changed += r[k] != (unsigned char)(k * 131u + 7u);
        }
        CHECK(changed == 0, "gc_big_move(%zu): %zu bytes changed", n, changed);
        CHECK(n >= GC_HUGE_PAGE_BYTES || (r == q && mapped == 0), "gc_big_move(%zu) moved a small block", n);
        gc_big_free(r, mapped);
    }
    /* long triangles in 64^3 cells: 2 MiB of cells (8 bytes each) and over 2 MiB of packs */
    mesh_buf m = random_soup(150, 0.6, 3);
    const int64_t n = 2000;
    double *o = malloc((size_t)n * 3 * sizeof(double)), *d = malloc((size_t)n * 3 * sizeof(double));
    double lo[3], hi[3];
    char err[GC_ERROR_LEN];
    gc_mesh mesh = as_mesh(&m);
    CHECK(gc_mesh_box(&mesh, lo, hi, err) == GC_OK, "box: %s", err);
    random_rays(n, lo, hi, 104, o, d);
    gc_build_params p = gc_build_params_default();
    p.resolution[0] = p.resolution[1] = p.resolution[2] = 64;
    gc_grid *g = NULL;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_OK, "big grid: %s", err);
    gc_grid_info info = {0};
    if (g) {
        gc_grid_get_info(g, &info);
    }
    CHECK(info.memory_bytes > 2 * (int64_t)GC_HUGE_PAGE_BYTES, "the big grid holds %lld bytes, want more than 4 MiB",
          (long long)info.memory_bytes);
    gc_grid_free(g);
    compare_with_brute(&m, &p, n, o, d, "big grid (huge pages)");
    free(o), free(d);
    mesh_free(&m);
}

/* Freed mappings kept for reuse (bigmem.c): a kept mapping serves a later request
 * of half to all of its length, zeroed unless asked raw; the oldest go past
 * GC_BIG_KEEP mappings or GC_BIG_KEEP_BYTES; one over the limit is not kept;
 * gc_release_memory empties the list.  A grid built into another grid's kept
 * packs has its last pack's spare lanes zero and agrees with brute force. */
static void test_kept_mappings(void)
{
#if defined(__linux__)
    const size_t mib = (size_t)1 << 20;
    int count = -1;
    size_t bytes = 1;
    gc_release_memory();
    gc_big_kept(&count, &bytes);
    CHECK(count == 0 && bytes == 0, "after gc_release_memory: %d kept, %zu bytes", count, bytes);
    size_t m1 = 0, m2 = 0;
    unsigned char *p = gc_big_alloc(3 * mib, &m1);
    if (!p || !m1) {
        CHECK(0, "gc_big_alloc(3 MiB) gave no mapping (%zu)", m1);
        gc_big_free(p, m1);
        return;
    }
    memset(p, 0xab, m1);
    gc_big_free(p, m1);
    gc_big_kept(&count, &bytes);
    CHECK(count == 1 && bytes == m1, "a freed 3 MiB mapping: %d kept, %zu bytes (want 1, %zu)", count, bytes, m1);
    unsigned char *q = gc_big_alloc(3 * mib + 5, &m2);
    size_t nonzero = 0;
    for (size_t k = 0; q && k < 3 * mib + 5; ++k) {
        nonzero += q[k] != 0;
    }
    CHECK(q == p && m2 == m1, "a request of the same length did not take the kept mapping");
    CHECK(nonzero == 0, "a kept mapping reused: %zu bytes not zero", nonzero);
    gc_big_kept(&count, &bytes);
    CHECK(count == 0 && bytes == 0, "a kept mapping taken: %d still kept, %zu bytes", count, bytes);
    memset(q, 0xcd, m2);
    gc_big_free(q, m2);
    q = gc_big_alloc_raw(2 * mib + 1, &m2, 0); /* 4 MiB: the kept one, as it was left */
    CHECK(q == p && m2 == m1 && q[0] == 0xcd && q[m2 - 1] == 0xcd, "a raw request of 4 MiB: %p (kept %p)",
          (void *)q, (void *)p);
    gc_big_free(q, m2);
    q = gc_big_alloc(2 * mib, &m2); /* half the kept 4 MiB, still taken */
    CHECK(q == p, "a request of half the kept length did not take it");
    gc_big_free(q, m2);
    unsigned char *big = gc_big_alloc(16 * mib, &m2); /* the 4 MiB kept one too short */
    CHECK(big != p, "a 16 MiB request took a kept 4 MiB mapping");
    gc_big_free(big, m2);
    q = gc_big_alloc(2 * mib, &m2); /* the kept 4 MiB one, not the 16 MiB one (8 times over) */
    CHECK(q == p, "a 2 MiB request did not take the smallest kept mapping long enough");
    gc_big_free(q, m2);
    gc_release_memory();
    /* at most GC_BIG_KEEP, the oldest dropped: the kept ones are the last freed */
    unsigned char *freed[GC_BIG_KEEP + 2];
    size_t freed_m[GC_BIG_KEEP + 2];
    for (int k = 0; k < GC_BIG_KEEP + 2; ++k) {
        freed[k] = gc_big_alloc(2 * mib, &freed_m[k]);
    }
    for (int k = 0; k < GC_BIG_KEEP + 2; ++k) {
        gc_big_free(freed[k], freed_m[k]);
    }
    gc_big_kept(&count, &bytes);
    CHECK(count == GC_BIG_KEEP && bytes == (size_t)GC_BIG_KEEP * 2 * mib, "%d freed: %d kept, %zu bytes",
          GC_BIG_KEEP + 2, count, bytes);
    unsigned char *taken[GC_BIG_KEEP];
    size_t taken_m[GC_BIG_KEEP];
    int newest = 0;
    for (int k = 0; k < GC_BIG_KEEP; ++k) {
        taken[k] = gc_big_alloc_raw(2 * mib, &taken_m[k], 0);
        for (int j = 2; j < GC_BIG_KEEP + 2; ++j) {
            newest += taken[k] == freed[j];
        }
    }
    CHECK(newest == GC_BIG_KEEP, "%d of the %d kept mappings are the last freed", newest, GC_BIG_KEEP);
    for (int k = 0; k < GC_BIG_KEEP; ++k) {
        gc_big_free(taken[k], taken_m[k]);
    }
    /* at most GC_BIG_KEEP_BYTES in all (never touched: only address space), and one larger never kept */
    const size_t part = GC_BIG_KEEP_BYTES / 2 - mib;
    unsigned char *h1 = gc_big_alloc(part, &m1), *h2 = gc_big_alloc(part, &m2);
    size_t m3 = 0;
    unsigned char *h3 = gc_big_alloc(GC_BIG_KEEP_BYTES + 1, &m3);
    CHECK(h1 && h2 && h3, "address space for %zu bytes", 2 * part + GC_BIG_KEEP_BYTES);
    gc_big_free(h1, m1);
    gc_big_free(h2, m2);
    gc_big_kept(&count, &bytes);
    CHECK(bytes <= GC_BIG_KEEP_BYTES && count >= 2, "two of %zu MiB freed: %d kept, %zu bytes", part / mib, count,
          bytes);
    gc_big_free(h3, m3);
    size_t bytes2 = 0;
    gc_big_kept(&count, &bytes2);
    CHECK(bytes2 == bytes, "a mapping over GC_BIG_KEEP_BYTES was kept (%zu -> %zu bytes)", bytes, bytes2);
    gc_release_memory();
    gc_big_kept(&count, &bytes);
    CHECK(count == 0 && bytes == 0, "gc_release_memory left %d mappings, %zu bytes", count, bytes);

    /* a grid built into another grid's packs: long triangles in 64^3 cells (over 2 MiB of
     * packs), then other triangles, a reference count that leaves spare lanes */
    mesh_buf a = random_soup(150, 0.6, 3);
    char err[GC_ERROR_LEN] = "";
    gc_mesh mesh_a = as_mesh(&a);
    gc_build_params p64 = gc_build_params_default();
    p64.resolution[0] = p64.resolution[1] = p64.resolution[2] = 64;
    gc_grid *ga = NULL;
    CHECK(gc_grid_build(&mesh_a, &p64, &ga, err) == GC_OK, "grid to be freed: %s", err);
    if (!ga) {
        mesh_free(&a);
        return;
    }
    for (int64_t k = 0; k < (int64_t)(GC_PACK_BYTES(ga->n_refs) / sizeof(gc_pack)) * GC_LANES; ++k) {
        ga->ref_tris[k / GC_LANES].c[0][k % GC_LANES] = 0.5; /* stale data for the spare lanes to lose */
        ga->ref_tris[k / GC_LANES].id[k % GC_LANES] = 7;
    }
    const gc_pack *old_packs = ga->ref_tris;
    gc_grid_free(ga);
    int spare_checked = 0;
    for (int32_t r = 64; r >= 56 && !spare_checked; --r) {
        mesh_buf b = random_soup(149, 0.6, 5);
        gc_mesh mesh_b = as_mesh(&b);
        gc_build_params pb = p64;
        pb.resolution[0] = pb.resolution[1] = pb.resolution[2] = r;
        gc_grid *gb = NULL;
        CHECK(gc_grid_build(&mesh_b, &pb, &gb, err) == GC_OK, "grid in kept memory: %s", err);
        if (gb && gb->ref_tris == old_packs && gb->n_refs % GC_LANES != 0) {
            const gc_pack *last = &gb->ref_tris[gb->n_refs / GC_LANES];
            size_t stale = 0;
            for (int lane = (int)(gb->n_refs % GC_LANES); lane < GC_LANES; ++lane) {
                for (int c = 0; c < 9; ++c) {
                    stale += last->c[c][lane] != 0.0;
                }
                stale += last->id[lane] != 0;
            }
            CHECK(stale == 0, "%zu values of the last pack's spare lanes kept from the grid before", stale);
            spare_checked = 1;
            const int64_t n = 2000;
            double *o = malloc((size_t)n * 3 * sizeof(double)), *d = malloc((size_t)n * 3 * sizeof(double));
            double lo[3], hi[3];
            CHECK(gc_mesh_box(&mesh_b, lo, hi, err) == GC_OK, "box: %s", err);
            random_rays(n, lo, hi, 105, o, d);
            gc_grid_free(gb);
            gb = NULL;
            compare_with_brute(&b, &pb, n, o, d, "grid in a kept mapping");
            free(o), free(d);
        }
        gc_grid_free(gb);
        mesh_free(&b);
    }
    CHECK(spare_checked, "no grid of 56^3-64^3 cells took the kept packs with spare lanes");
    mesh_free(&a);
    gc_release_memory();
#endif
}

/* Explicit resolutions at depths 1 and 2: the grid holds exactly the cells the two
 * tables give, agrees with brute force, and bad tables are refused. */
static void test_explicit_depth2_resolutions(void)
{
    mesh_buf m = random_soup(300, 0.3, 11);
    gc_mesh mesh = as_mesh(&m);
    char err[GC_ERROR_LEN];
    const int32_t top[3] = {3, 2, 4};
    const int64_t n_top = 3 * 2 * 4;
    int32_t sub1[24 * 3];
    int64_t rows2 = 0;
    rng_seed(12);
    for (int64_t c = 0; c < n_top; ++c) { /* every third top cell a leaf, the rest 1..3 per axis */
        for (int i = 0; i < 3; ++i) {
            sub1[3 * c + i] = (c % 3 == 2) ? 0 : 1 + (int32_t)(3.0 * rng_uniform());
        }
        if (c % 3 != 2) {
            rows2 += (int64_t)sub1[3 * c] * sub1[3 * c + 1] * sub1[3 * c + 2];
        }
    }
    int32_t *sub2 = malloc((size_t)rows2 * 3 * sizeof(int32_t));
    int64_t cells = n_top, cells2 = 0;
    for (int64_t c = 0; c < n_top; ++c) {
        if (c % 3 != 2) {
            cells += (int64_t)sub1[3 * c] * sub1[3 * c + 1] * sub1[3 * c + 2];
        }
    }
    for (int64_t r = 0; r < rows2; ++r) { /* half the depth-1 cells a 1..4-per-axis subgrid */
        int leaf = rng_uniform() < 0.5;
        for (int i = 0; i < 3; ++i) {
            sub2[3 * r + i] = leaf ? 0 : 1 + (int32_t)(4.0 * rng_uniform());
        }
        if (!leaf) {
            cells2 += (int64_t)sub2[3 * r] * sub2[3 * r + 1] * sub2[3 * r + 2];
        }
    }
    gc_build_params p = gc_build_params_default();
    memcpy(p.resolution, top, sizeof p.resolution);
    p.levels = 3;
    p.subgrid_resolutions = sub1;
    p.subgrid_resolutions2 = sub2;
    p.n_subgrid_resolutions2 = rows2;
    gc_grid *g = NULL;
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_OK, "explicit depth-2 table refused: %s", err);
    if (g) {
        gc_grid_info info;
        gc_grid_get_info(g, &info);
        CHECK(info.n_cells == cells + cells2, "explicit depth-2 table: %lld cells, the tables give %lld",
              (long long)info.n_cells, (long long)(cells + cells2));
        gc_grid_free(g);
    }
    const int64_t n = 1500;
    double *o = malloc((size_t)n * 3 * sizeof(double)), *d = malloc((size_t)n * 3 * sizeof(double));
    double lo[3], hi[3];
    CHECK(gc_mesh_box(&mesh, lo, hi, err) == GC_OK, "box: %s", err);
    random_rays(n, lo, hi, 13, o, d);
    for (int isect = 0; isect < 2; ++isect) {
        p.intersector = isect ? GC_WATERTIGHT : GC_MOLLER_TRUMBORE;
        compare_with_brute(&m, &p, n, o, d, isect ? "explicit depth 2, watertight" : "explicit depth 2, MT");
    }
    p.intersector = GC_WATERTIGHT;

    /* refusals: a row short, a row over, no depth-1 table, two levels */
    g = (gc_grid *)&err;
    p.n_subgrid_resolutions2 = rows2 - 1;
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && g == NULL && strstr(err, "rows"),
          "a depth-2 table a row short not refused: %s", err);
    p.n_subgrid_resolutions2 = rows2 + 1;
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && strstr(err, "rows"),
          "a depth-2 table a row over not refused: %s", err);
    p.n_subgrid_resolutions2 = rows2;
    p.subgrid_resolutions = NULL;
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && strstr(err, "needs subgrid_resolutions"),
          "a depth-2 table without a depth-1 table not refused: %s", err);
    p.subgrid_resolutions = sub1;
    p.levels = 2;
    err[0] = 0;
    CHECK(gc_grid_build(&mesh, &p, &g, err) == GC_ERR_ARGUMENT && strstr(err, "levels >= 3"),
          "a depth-2 table with two levels not refused: %s", err);
    free(o), free(d), free(sub2);
    mesh_free(&m);
}


/* The AVX2 preparation and box clip against the scalar ones, bit for bit: directions with
 * components of +0, -0, subnormals (flushed), ties between the largest components, huge
 * coordinates whose slab distances overflow to inf (a NaN end after widening), origins on
 * the box's faces, flat boxes. */
#if defined(GC_HAVE_AVX2_RAY)
GC_AVX2_RAY static void prepare_avx2(gc_ray *r, const double *o, const double *d) { gc_ray_prepare_avx2(r, o, d); }
GC_AVX2_RAY static int clip_avx2(const gc_ray *r, const double *lo, const double *hi, double *t0, double *t1)
{
    return gc_ray_box_clip_avx2(r, lo, hi, t0, t1);
}

static int same_bits(double a, double b) { return memcmp(&a, &b, sizeof a) == 0; }

static double pick_component(int kind, double scale)
{
    switch (kind) {
    case 0: return 0.0;
    case 1: return -0.0;
    case 2: return (rng_uniform() - 0.5) * 1e-310; /* subnormal: flushed to +0 */
    case 3: return rng_uniform() < 0.5 ? 1.0 : -1.0; /* ties with another axis */
    default: return (rng_uniform() - 0.5) * scale;
    }
}
#endif

static void test_ray_setup_avx2(void)
{
#if defined(GC_HAVE_AVX2_RAY)
    __builtin_cpu_init();
    if (!__builtin_cpu_supports("avx2")) {
        printf("ray setup on AVX2: not checked (this CPU has no AVX2)\n");
        return;
    }
    int clipped = 0, parallel = 0, nan_ends = 0;
    for (int k = 0; k < 200000; ++k) {
        rng_seed(0xC11Bu + (uint64_t)k);
        const double scale = (k % 7 == 0) ? 1e300 : (k % 7 == 1) ? 1e-20 : 10.0;
        const double dscale = (k % 7 == 0) ? 1e-10 : scale; /* slab distances past DBL_MAX */
        double lo[3], hi[3], o[3], d[3];
        for (int i = 0; i < 3; ++i) {
            lo[i] = (rng_uniform() - 0.5) * scale;
            hi[i] = (k % 11 == 0 && i == 1) ? lo[i] : lo[i] + rng_uniform() * scale;
            o[i] = (k % 5 == 0) ? (rng_uniform() < 0.5 ? lo[i] : hi[i]) : (rng_uniform() - 0.5) * 3.0 * scale;
            d[i] = pick_component(rng_uniform() < 0.3 ? (int)(rng_uniform() * 4.0) : 4, dscale);
        }
        if (d[0] == 0.0 && d[1] == 0.0 && d[2] == 0.0) {
            d[k % 3] = 1.0;
        }
        gc_ray a, b;
        gc_ray_prepare(&a, o, d);
        prepare_avx2(&b, o, d);
        int same = a.kx == b.kx && a.ky == b.ky && a.kz == b.kz && same_bits(a.sx, b.sx) && same_bits(a.sy, b.sy) &&
                   same_bits(a.sz, b.sz);
        for (int i = 0; i < 3; ++i) {
            same = same && same_bits(a.o[i], b.o[i]) && same_bits(a.d[i], b.d[i]) && same_bits(a.inv_d[i], b.inv_d[i]);
        }
        CHECK(same, "case %d: the AVX2 preparation differs from the scalar one", k);
        double ta = 0.0, tb = INFINITY, va = 0.0, vb = INFINITY;
        const int hit = gc_ray_box_clip(&a, lo, hi, &ta, &tb);
        const int vhit = clip_avx2(&a, lo, hi, &va, &vb);
        CHECK(hit == vhit && same_bits(ta, va) && same_bits(tb, vb),
              "case %d: the AVX2 clip gives %d [%.17g, %.17g], the scalar one %d [%.17g, %.17g]", k, vhit, va, vb,
              hit, ta, tb);
        clipped += hit;
        parallel += a.d[0] == 0.0 || a.d[1] == 0.0 || a.d[2] == 0.0;
        for (int i = 0; i < 3; ++i) {
            const double tn = (lo[i] - a.o[i]) * a.inv_d[i], tf = (hi[i] - a.o[i]) * a.inv_d[i];
            nan_ends += a.d[i] != 0.0 && (isinf(tn) || isinf(tf));
        }
    }
    /* the cases reach what they are there for */
    CHECK(clipped > 1000 && parallel > 1000 && nan_ends > 100, "clipped %d, parallel %d, infinite slab ends %d",
          clipped, parallel, nan_ends);
    printf("ray setup on AVX2: 200000 rays as the scalar code prepares and clips them (%d clipped, %d with a zero "
           "component, %d infinite slab ends)\n",
           clipped, parallel, nan_ends);
#endif
}

int main(void)
{
    test_prepared_overlap();
    test_mesh_sums();
    test_refusals();
    test_memory_limit_counts_packs_once();
    test_isa_switch();
    test_ray_setup_avx2();
    test_threads_same_grid();
    test_face_order();
    test_unused_vertices();
    test_grids_match_brute_force();
    test_axis_parallel_and_cell_faces();
    test_watertight();
    test_scaled_scenes();
    test_visits_and_positions();
    test_explicit_depth2_resolutions();
    test_big_arrays();
    test_kept_mappings();
    printf("%d passed, %d failed\n", checks - failures, failures);
    return failures ? 1 : 0;
}
