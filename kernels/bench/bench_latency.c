/* bench_latency.c - load latency against working-set size, on a grid's kind of memory.
 *
 * A dependent pointer chase over a random single cycle through every cache
 * line of a block (each load's address is the previous load's value, so nothing
 * overlaps and no prefetcher can guess the next line), for blocks from 256 KiB
 * to 256 MiB allocated as a grid's packs are (gc_big_alloc: huge pages where
 * Linux grants them).  Prints the block size and the nanoseconds per load: the
 * knees are the cache levels a traversal's random reads actually meet on this
 * host, whatever the cache sizes the OS reports (a virtual machine may report
 * the host's whole last-level cache).  Seeded: two runs chase the same cycles.
 *
 *   bench_latency [loads per size]   (default 20,000,000)
 */
#define _POSIX_C_SOURCE 199309L
#include "gc_internal.h"

#include <stdio.h>
#include <stdlib.h>
#include <time.h>

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

int main(int argc, char **argv)
{
    const long long loads = argc > 1 ? atoll(argv[1]) : 20000000LL;
    if (loads < 1) {
        fprintf(stderr, "usage: bench_latency [loads per size >= 1]\n");
        return 2;
    }
    static const size_t kib[] = {256, 1024, 2048, 3072, 4096, 6144, 8192, 12288, 16384, 24576, 32768, 65536,
                                 131072, 262144};
    printf("%10s %12s\n", "KiB", "ns/load");
    for (size_t s = 0; s < sizeof kib / sizeof kib[0]; ++s) {
        const size_t bytes = kib[s] << 10, lines = bytes / 64;
        size_t mapped = 0;
        char *block = gc_big_alloc(bytes, &mapped);
        size_t *order = malloc(lines * sizeof *order);
        if (!block || !order) {
            fprintf(stderr, "bench_latency: out of memory at %zu KiB\n", kib[s]);
            gc_big_free(block, mapped);
            free(order);
            return 1;
        }
        /* a random order of the lines (Fisher-Yates, xorshift64 seeded by the size) */
        uint64_t x = 0x9e3779b97f4a7c15ull ^ (uint64_t)bytes;
        for (size_t i = 0; i < lines; ++i) {
            order[i] = i;
        }
        for (size_t i = lines - 1; i > 0; --i) {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            const size_t j = (size_t)(x % (uint64_t)(i + 1));
            const size_t t = order[i];
            order[i] = order[j];
            order[j] = t;
        }
        /* each line points at the next in that order: one cycle through all of them */
        for (size_t i = 0; i < lines; ++i) {
            *(char **)(block + order[i] * 64) = block + order[(i + 1) % lines] * 64;
        }
        char *p = block + order[0] * 64;
        for (size_t i = 0; i < lines; ++i) { /* one lap to warm the caches and the TLB */
            p = *(char **)p;
        }
        const double t0 = now_s();
        for (long long i = 0; i < loads; ++i) {
            p = *(char **)p;
        }
        const double t1 = now_s();
        /* p printed so the chase cannot be optimised away */
        printf("%10zu %12.1f   (end %p)\n", kib[s], (t1 - t0) / (double)loads * 1e9, (void *)p);
        gc_big_free(block, mapped);
        free(order);
    }
    return 0;
}
