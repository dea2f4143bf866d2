/* bench_setup.c - what a ray costs before and between its cells: the timed twin over an
 * empty grid of m x m x m cells in the unit box.
 *
 *   bench_setup [m ...]        (default: 1 8)
 *
 * 20,000 rays from a sphere of radius 2 about the box's centre towards uniform points in
 * the box (seeded), traced by gc_bench_intersect; the best of seven timings of 200 loops
 * (wall clock), in ns a ray.  With m = 1 every ray takes its preparation, the box clip, the
 * walk's entry and one empty cell: the per-ray fixed cost the calibration calls T_setup;
 * a larger m adds empty steps.  No Python; run it pinned (taskset -c 1) on a quiet host.
 */
#include "gridcal.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define N_RAYS 20000
#define LOOPS 200
#define REPEATS 7

static uint64_t state = 88172645463325252ull;

static double u01(void)
{
    state ^= state << 13;
    state ^= state >> 7;
    state ^= state << 17;
    return (double)(state >> 11) * (1.0 / 9007199254740992.0);
}

static int run(int m, const double *o, const double *d)
{
    double v[3] = {0.0, 0.0, 0.0};
    int64_t f[3] = {0, 0, 0};
    gc_mesh mesh = {v, 1, f, 0}; /* no faces: the box and resolution are given */
    gc_build_params p = gc_build_params_default();
    p.has_box = 1;
    for (int i = 0; i < 3; ++i) {
        p.box_lo[i] = 0.0;
        p.box_hi[i] = 1.0;
        p.resolution[i] = m;
    }
    char err[256];
    gc_grid *g;
    if (gc_grid_build(&mesh, &p, &g, err) != GC_OK) {
        fprintf(stderr, "bench_setup: %s\n", err);
        return 1;
    }
    double best = INFINITY;
    for (int r = 0; r < REPEATS; ++r) {
        int64_t elapsed;
        double checksum;
        if (gc_bench_intersect(g, N_RAYS, o, d, LOOPS, &elapsed, &checksum, err) != GC_OK) {
            fprintf(stderr, "bench_setup: %s\n", err);
            gc_grid_free(g);
            return 1;
        }
        const double ns = (double)elapsed / LOOPS / N_RAYS;
        best = ns < best ? ns : best;
    }
    printf("%dx%dx%d empty cells: %.1f ns a ray (best of %d, %d rays x %d loops, %s)\n", m, m, m, best, REPEATS,
           N_RAYS, LOOPS, gc_traverse_isa());
    gc_grid_free(g);
    return 0;
}

int main(int argc, char **argv)
{
    double *o = malloc(sizeof(double) * 3 * N_RAYS), *d = malloc(sizeof(double) * 3 * N_RAYS);
    if (!o || !d) {
        fprintf(stderr, "bench_setup: out of memory\n");
        return 1;
    }
    for (int k = 0; k < N_RAYS; ++k) {
        const double z = 2.0 * u01() - 1.0, ph = 6.283185307179586 * u01(), s = sqrt(1.0 - z * z);
        const double oo[3] = {0.5 + 2.0 * s * cos(ph), 0.5 + 2.0 * s * sin(ph), 0.5 + 2.0 * z};
        const double to[3] = {u01(), u01(), u01()};
        double len = 0.0;
        for (int i = 0; i < 3; ++i) {
            len += (to[i] - oo[i]) * (to[i] - oo[i]);
        }
        len = sqrt(len);
        for (int i = 0; i < 3; ++i) {
            o[3 * k + i] = oo[i];
            d[3 * k + i] = (to[i] - oo[i]) / len;
        }
    }
    int status = 0;
    if (argc < 2) {
        status |= run(1, o, d);
        status |= run(8, o, d);
    }
    for (int a = 1; a < argc; ++a) {
        const int m = atoi(argv[a]);
        if (m < 1 || m > 1024) {
            fprintf(stderr, "bench_setup: cells an axis must be 1..1024, not '%s'\n", argv[a]);
            status = 1;
            continue;
        }
        status |= run(m, o, d);
    }
    free(o);
    free(d);
    return status;
}
