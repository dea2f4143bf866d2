/* bigmem.c - the allocation of a grid's large traversal arrays.
 *
 * A grid of many MB is read at random, a cell record and a few packs at a
 * time: with 4 KiB pages nearly every cell a ray enters beyond the TLB's reach
 * (a few MB) costs a page walk before its first load.  On Linux an array of at
 * least one huge page (2 MiB) is mapped on its own, aligned to a huge page and
 * marked MADV_HUGEPAGE before it is touched, so that the kernel backs it with
 * 2 MiB pages where transparent huge pages are enabled ("always" or
 * "madvise").  It is mapped rather than taken from malloc: glibc serves a
 * large block freed earlier from its heap, whose pages are already 4 KiB ones.
 * Elsewhere, below that size, or when the mapping fails, it is an ordinary
 * calloc.  The contents are the same either way: zeroed.
 */
#if defined(__linux__) && !defined(_GNU_SOURCE)
#define _GNU_SOURCE /* mmap's MAP_ANONYMOUS, madvise and MADV_HUGEPAGE under -std=c99 */
#endif
#include "gc_internal.h"

#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__linux__)
#include <sys/mman.h>
#endif

#if defined(__linux__) && defined(MADV_HUGEPAGE) && defined(MAP_ANONYMOUS)
#define GC_BIG_MAPPED 1
#else
#define GC_BIG_MAPPED 0
#endif

void *gc_big_alloc(size_t bytes, size_t *mapped)
{
    *mapped = 0;
#if GC_BIG_MAPPED
    if (bytes >= GC_HUGE_PAGE_BYTES) {
        const size_t page = GC_HUGE_PAGE_BYTES;
        const size_t len = (bytes + page - 1) & ~(page - 1);
        if (len >= bytes && len <= SIZE_MAX - page) {
            /* one huge page more than needed, then the unaligned head and the tail given back */
            char *raw = mmap(NULL, len + page, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
            if (raw != MAP_FAILED) {
                const size_t head = (page - (size_t)((uintptr_t)raw % page)) % page;
                char *p = raw + head;
                if (head) {
                    (void)munmap(raw, head);
                }
                (void)munmap(p + len, page - head); /* head < page: never empty */
                (void)madvise(p, len, MADV_HUGEPAGE); /* a hint: refused, the pages stay 4 KiB */
                *mapped = len;
                return p; /* anonymous pages read as zero */
            }
        }
    }
#endif
    return calloc(bytes ? bytes : 1, 1);
}

void gc_big_free(void *p, size_t mapped)
{
    if (!p) {
        return;
    }
#if GC_BIG_MAPPED
    if (mapped) {
        (void)munmap(p, mapped);
        return;
    }
#else
    (void)mapped;
#endif
    free(p);
}

void *gc_big_move(void *p, size_t bytes, size_t *mapped)
{
    *mapped = 0;
    if (p && bytes >= GC_HUGE_PAGE_BYTES) {
        size_t m = 0;
        void *q = gc_big_alloc(bytes, &m);
        if (q && m) {
            memcpy(q, p, bytes);
            free(p);
            *mapped = m;
            return q;
        }
        free(q); /* an ordinary block: p serves as well */
    }
    return p;
}
