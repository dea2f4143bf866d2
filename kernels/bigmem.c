/* bigmem.c - the allocation of a grid's large traversal arrays.
 *
 * A grid of many MB is read at random, a few lines of a cell and its packs at
 * a time: with 4 KiB pages nearly every cell a ray enters beyond the TLB's
 * reach (a few MB) costs a page walk before its first load.  On Linux an
 * array of at least one huge page (2 MiB) is aligned to one and marked
 * MADV_HUGEPAGE, so that the kernel backs it with 2 MiB pages where
 * transparent huge pages are enabled ("always" or "madvise"); elsewhere, or
 * when the kernel declines, it is an ordinary allocation.  The contents are
 * the same either way: zeroed, as calloc's.
 */
#if defined(__linux__) && !defined(_GNU_SOURCE)
#define _GNU_SOURCE /* madvise and MADV_HUGEPAGE under -std=c99 */
#endif
#include "gc_internal.h"

#include <stdlib.h>
#include <string.h>
#if defined(__linux__)
#include <sys/mman.h>
#endif

void *gc_big_calloc(size_t bytes)
{
#if defined(__linux__) && defined(MADV_HUGEPAGE)
    if (bytes >= GC_HUGE_PAGE_BYTES) {
        const size_t rounded = (bytes + GC_HUGE_PAGE_BYTES - 1) & ~(GC_HUGE_PAGE_BYTES - 1);
        void *p = NULL;
        if (rounded < bytes || posix_memalign(&p, GC_HUGE_PAGE_BYTES, rounded) != 0) {
            return NULL;
        }
        (void)madvise(p, rounded, MADV_HUGEPAGE); /* a hint: refused, the pages stay 4 KiB */
        memset(p, 0, rounded);
        return p;
    }
#endif
    return calloc(bytes ? bytes : 1, 1);
}

void *gc_big_move(void *p, size_t bytes)
{
#if defined(__linux__) && defined(MADV_HUGEPAGE)
    if (p && bytes >= GC_HUGE_PAGE_BYTES) {
        void *q = gc_big_calloc(bytes);
        if (q) {
            memcpy(q, p, bytes);
            free(p);
            return q;
        }
    }
#else
    (void)bytes;
#endif
    return p;
}
