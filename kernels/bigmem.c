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
 *
 * A freed mapping is kept for the next grid (at most GC_BIG_KEEP of them,
 * GC_BIG_KEEP_BYTES in all) rather than unmapped: a fresh mapping's pages are
 * zeroed by the kernel at their first touch, and on a virtual machine that
 * returns free huge pages to its host (free page reporting) the host must back
 * each one again, at a few times the cost of the zeroing.  A process that builds
 * grid after grid (a calibration, a sweep of resolutions) pays that once; a kept
 * mapping is zeroed here on reuse, at memset's speed, unless its caller writes
 * all of it anyway (gc_big_alloc_raw).  gc_release_memory unmaps
 * the kept ones.
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
#if !defined(GC_NO_THREADS)
#include <pthread.h>
#endif

#if defined(__linux__) && defined(MADV_HUGEPAGE) && defined(MAP_ANONYMOUS)
#define GC_BIG_MAPPED 1
#else
#define GC_BIG_MAPPED 0
#endif

#if GC_BIG_MAPPED
/* The kept mappings, most recently freed last; kept_lock guards them. */
static struct {
    void *p;
    size_t len;
} kept[GC_BIG_KEEP];
static int n_kept;
static size_t kept_bytes;
#if !defined(GC_NO_THREADS)
static pthread_mutex_t kept_lock = PTHREAD_MUTEX_INITIALIZER;
#define KEPT_LOCK() pthread_mutex_lock(&kept_lock)
#define KEPT_UNLOCK() pthread_mutex_unlock(&kept_lock)
#else
#define KEPT_LOCK() ((void)0)
#define KEPT_UNLOCK() ((void)0)
#endif

static void kept_drop(int i)
{
    kept_bytes -= kept[i].len;
    for (int k = i + 1; k < n_kept; ++k) {
        kept[k - 1] = kept[k];
    }
    --n_kept;
}

/* The oldest kept mappings taken out of the list (kept_lock held) until one more of `room`
 * bytes fits beside the rest, or every one with `all`; their count, into out and out_len,
 * for the caller to unmap once the lock is released. */
static int kept_evict(int all, size_t room, void *out[GC_BIG_KEEP], size_t out_len[GC_BIG_KEEP])
{
    int n = 0;
    while (n_kept > 0 && (all || n_kept == GC_BIG_KEEP || kept_bytes + room > GC_BIG_KEEP_BYTES)) {
        out[n] = kept[0].p;
        out_len[n++] = kept[0].len;
        kept_drop(0);
    }
    return n;
}

/* The smallest kept mapping of len to 2 len bytes, taken out of the list; NULL if none. */
static void *kept_take(size_t len, size_t *got)
{
    void *p = NULL;
    KEPT_LOCK();
    int best = -1;
    for (int i = 0; i < n_kept; ++i) {
        if (kept[i].len >= len && kept[i].len / 2 <= len && (best < 0 || kept[i].len < kept[best].len)) {
            best = i;
        }
    }
    if (best >= 0) {
        p = kept[best].p;
        *got = kept[best].len;
        kept_drop(best);
    }
    KEPT_UNLOCK();
    return p;
}
#endif

void *gc_big_alloc(size_t bytes, size_t *mapped)
{
    return gc_big_alloc_raw(bytes, mapped, 1);
}

void *gc_big_alloc_raw(size_t bytes, size_t *mapped, int zero)
{
    *mapped = 0;
#if GC_BIG_MAPPED
    if (bytes >= GC_HUGE_PAGE_BYTES) {
        const size_t page = GC_HUGE_PAGE_BYTES;
        const size_t len = (bytes + page - 1) & ~(page - 1);
        if (len >= bytes && len <= SIZE_MAX - page) {
            size_t got = 0;
            char *q = kept_take(len, &got);
            if (q) {
                if (zero) {
                    memset(q, 0, bytes); /* the rest of it is never read */
                }
                *mapped = got;
                return q;
            }
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
#else
    (void)zero;
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
        if (mapped > GC_BIG_KEEP_BYTES) { /* over the limit alone: never kept */
            (void)munmap(p, mapped);
            return;
        }
        /* kept; the oldest kept go to make room, unmapped outside the lock */
        void *out[GC_BIG_KEEP];
        size_t out_len[GC_BIG_KEEP];
        KEPT_LOCK();
        const int n_out = kept_evict(0, mapped, out, out_len);
        kept[n_kept].p = p;
        kept[n_kept++].len = mapped;
        kept_bytes += mapped;
        KEPT_UNLOCK();
        for (int k = 0; k < n_out; ++k) {
            (void)munmap(out[k], out_len[k]);
        }
        return;
    }
#else
    (void)mapped;
#endif
    free(p);
}

void gc_big_kept(int *count, size_t *bytes)
{
#if GC_BIG_MAPPED
    KEPT_LOCK();
    *count = n_kept;
    *bytes = kept_bytes;
    KEPT_UNLOCK();
#else
    *count = 0;
    *bytes = 0;
#endif
}

void gc_release_memory(void)
{
#if GC_BIG_MAPPED
    void *out[GC_BIG_KEEP];
    size_t out_len[GC_BIG_KEEP];
    KEPT_LOCK();
    const int n = kept_evict(1, 0, out, out_len);
    KEPT_UNLOCK();
    for (int k = 0; k < n; ++k) {
        (void)munmap(out[k], out_len[k]);
    }
#endif
}

void *gc_big_move(void *p, size_t bytes, size_t *mapped)
{
    *mapped = 0;
    if (p && bytes >= GC_HUGE_PAGE_BYTES) {
        size_t m = 0;
        void *q = gc_big_alloc_raw(bytes, &m, 0); /* all of it copied over */
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
