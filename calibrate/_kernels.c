/* _kernels.c - the thin binding between Python and kernels/ (gridcal.h).
 *
 * Rays and meshes cross once per batch as contiguous numpy arrays; every loop
 * runs in C with the GIL released.  Validation with readable messages lives in
 * calibrate/_grid.py; this layer only refuses what would be unsafe to pass on,
 * and turns gc_status codes into Python exceptions (ValueError for bad input,
 * OverflowError for sizes, MemoryError for allocation).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#define NPY_NO_DEPRECATED_API NPY_1_7_API_VERSION
#include <numpy/arrayobject.h>

#include "gridcal.h"

#ifndef GRIDCAL_CFLAGS
#define GRIDCAL_CFLAGS "unknown"
#endif

static const char *CAPSULE_NAME = "gridcal.grid";

static PyObject *raise_status(gc_status st, const char *err)
{
    PyObject *type = PyExc_RuntimeError;
    switch (st) {
    case GC_ERR_ARGUMENT:
        type = PyExc_ValueError;
        break;
    case GC_ERR_OVERFLOW:
        type = PyExc_OverflowError;
        break;
    case GC_ERR_MEMORY_LIMIT:
        type = PyExc_MemoryError;
        break;
    case GC_ERR_NO_MEMORY:
        type = PyExc_MemoryError;
        break;
    default:
        break;
    }
    PyErr_SetString(type, err && err[0] ? err : "kernel error");
    return NULL;
}

/* A C-contiguous array of `type` with shape (n, 3), or NULL with an exception. */
static PyArrayObject *as_rows3(PyObject *obj, int type, const char *what)
{
    PyArrayObject *a = (PyArrayObject *)PyArray_FROM_OTF(obj, type, NPY_ARRAY_IN_ARRAY);
    if (!a) {
        return NULL;
    }
    if (PyArray_NDIM(a) != 2 || PyArray_DIM(a, 1) != 3) {
        PyErr_Format(PyExc_ValueError, "%s must have shape (n, 3)", what);
        Py_DECREF(a);
        return NULL;
    }
    return a;
}

static void grid_capsule_free(PyObject *cap)
{
    gc_grid *g = PyCapsule_GetPointer(cap, CAPSULE_NAME);
    gc_grid_free(g);
}

static gc_grid *get_grid(PyObject *cap)
{
    return PyCapsule_GetPointer(cap, CAPSULE_NAME);
}

/* The grid of a call whose only argument is a grid capsule. */
static gc_grid *grid_arg(PyObject *args)
{
    PyObject *cap;
    if (!PyArg_ParseTuple(args, "O", &cap)) {
        return NULL;
    }
    return get_grid(cap);
}

static int read_doubles(PyObject *seq, double *out, Py_ssize_t n, const char *what)
{
    PyObject *fast = PySequence_Fast(seq, what);
    if (!fast) {
        return -1;
    }
    if (PySequence_Fast_GET_SIZE(fast) != n) {
        PyErr_Format(PyExc_ValueError, "%s needs %zd values", what, n);
        Py_DECREF(fast);
        return -1;
    }
    for (Py_ssize_t i = 0; i < n; ++i) {
        out[i] = PyFloat_AsDouble(PySequence_Fast_GET_ITEM(fast, i));
        if (PyErr_Occurred()) {
            Py_DECREF(fast);
            return -1;
        }
    }
    Py_DECREF(fast);
    return 0;
}

static PyObject *py_build(PyObject *self, PyObject *args, PyObject *kw)
{
    (void)self;
    static char *kwlist[] = {"vertices", "faces", "resolution", "intersector", "insertion",
                             "mailbox", "box", "memory_limit", "levels", "threshold",
                             "level_scale", "level_exponent", "subgrid_resolutions",
                             "rule_max_axis", "threads", "subgrid_resolutions2", NULL};
    PyObject *vobj, *fobj, *box = Py_None, *scale = Py_None, *expo = Py_None, *subres = Py_None;
    PyObject *subres2 = Py_None;
    int rx, ry, rz, intersector = GC_WATERTIGHT, insertion = GC_INSERT_EXACT, mailbox = 0, levels = 1;
    int rule_max_axis = 256, threads = 1;
    unsigned long long memory_limit = 0;
    unsigned int threshold = 2;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "OO(iii)|iipOKiIOOOiiO", kwlist, &vobj, &fobj, &rx, &ry,
                                     &rz, &intersector, &insertion, &mailbox, &box, &memory_limit,
                                     &levels, &threshold, &scale, &expo, &subres, &rule_max_axis,
                                     &threads, &subres2)) {
        return NULL;
    }
    gc_build_params p = gc_build_params_default();
    p.resolution[0] = rx, p.resolution[1] = ry, p.resolution[2] = rz;
    p.intersector = (gc_intersector)intersector;
    p.insertion = (gc_insertion)insertion;
    p.mailbox = mailbox;
    p.memory_limit_bytes = memory_limit;
    p.levels = levels;
    p.subdivide_threshold = threshold;
    p.rule_max_axis = rule_max_axis;
    p.threads = threads;
    if (box != Py_None) {
        double b[6];
        if (read_doubles(box, b, 6, "box (lo x, y, z, hi x, y, z)") < 0) {
            return NULL;
        }
        p.has_box = 1;
        for (int i = 0; i < 3; ++i) {
            p.box_lo[i] = b[i];
            p.box_hi[i] = b[3 + i];
        }
    }
    if (scale != Py_None && read_doubles(scale, p.level_scale, GC_MAX_LEVELS, "level_scale") < 0) {
        return NULL;
    }
    if (expo != Py_None && read_doubles(expo, p.level_exponent, GC_MAX_LEVELS, "level_exponent") < 0) {
        return NULL;
    }
    PyArrayObject *v = as_rows3(vobj, NPY_FLOAT64, "vertices");
    if (!v) {
        return NULL;
    }
    PyArrayObject *f = as_rows3(fobj, NPY_INT64, "faces");
    if (!f) {
        Py_DECREF(v);
        return NULL;
    }
    PyArrayObject *sr = NULL;
    if (subres != Py_None) {
        sr = as_rows3(subres, NPY_INT32, "subgrid_resolutions");
        if (!sr) {
            Py_DECREF(v);
            Py_DECREF(f);
            return NULL;
        }
        if ((long long)PyArray_DIM(sr, 0) != (long long)rx * ry * rz) {
            PyErr_SetString(PyExc_ValueError,
                            "subgrid_resolutions needs one row per top-level cell (nx*ny*nz rows)");
            Py_DECREF(v);
            Py_DECREF(f);
            Py_DECREF(sr);
            return NULL;
        }
        p.subgrid_resolutions = (const int32_t *)PyArray_DATA(sr);
    }
    PyArrayObject *sr2 = NULL;
    if (subres2 != Py_None) {
        sr2 = as_rows3(subres2, NPY_INT32, "subgrid_resolutions2");
        if (!sr2) {
            Py_DECREF(v);
            Py_DECREF(f);
            Py_XDECREF(sr);
            return NULL;
        }
        p.subgrid_resolutions2 = (const int32_t *)PyArray_DATA(sr2);
        p.n_subgrid_resolutions2 = (int64_t)PyArray_DIM(sr2, 0);
    }
    gc_mesh mesh = {(const double *)PyArray_DATA(v), (int64_t)PyArray_DIM(v, 0),
                    (const int64_t *)PyArray_DATA(f), (int64_t)PyArray_DIM(f, 0)};
    gc_grid *g = NULL;
    char err[GC_ERROR_LEN] = "";
    gc_status st;
    Py_BEGIN_ALLOW_THREADS st = gc_grid_build(&mesh, &p, &g, err);
    Py_END_ALLOW_THREADS Py_DECREF(v);
    Py_DECREF(f);
    Py_XDECREF(sr);
    Py_XDECREF(sr2);
    if (st != GC_OK) {
        return raise_status(st, err);
    }
    PyObject *cap = PyCapsule_New(g, CAPSULE_NAME, grid_capsule_free);
    if (!cap) {
        gc_grid_free(g);
    }
    return cap;
}

static PyObject *py_info(PyObject *self, PyObject *args)
{
    (void)self;
    gc_grid *g = grid_arg(args);
    if (!g) {
        return NULL;
    }
    gc_grid_info info;
    gc_grid_get_info(g, &info);
    return Py_BuildValue(
        "{s:L,s:L,s:L,s:L,s:L,s:L,s:i,s:(iii),s:(ddd),s:(ddd),s:i,s:O}", "n_triangles",
        (long long)info.n_triangles, "n_nodes", (long long)info.n_nodes, "n_cells",
        (long long)info.n_cells, "n_refs", (long long)info.n_refs, "n_empty_cells",
        (long long)info.n_empty_cells, "memory_bytes", (long long)info.memory_bytes, "levels",
        (int)info.levels, "resolution", info.resolution[0], info.resolution[1], info.resolution[2],
        "box_lo", info.box_lo[0], info.box_lo[1], info.box_lo[2], "box_hi", info.box_hi[0],
        info.box_hi[1], info.box_hi[2], "intersector", (int)info.intersector, "mailbox",
        info.mailbox ? Py_True : Py_False);
}

static PyObject *py_top_counts(PyObject *self, PyObject *args)
{
    (void)self;
    gc_grid *g = grid_arg(args);
    if (!g) {
        return NULL;
    }
    gc_grid_info info;
    gc_grid_get_info(g, &info);
    npy_intp dims[3] = {info.resolution[2], info.resolution[1], info.resolution[0]};
    PyArrayObject *out = (PyArrayObject *)PyArray_SimpleNew(3, dims, NPY_INT64);
    if (!out) {
        return NULL;
    }
    gc_grid_top_counts(g, (int64_t *)PyArray_DATA(out));
    return (PyObject *)out;
}

/* Parse (grid, origins, directions) into arrays; returns 0 on success. */
static int parse_rays(PyObject *args, const char *fmt, PyObject **cap, PyArrayObject **o,
                      PyArrayObject **d, long long *loops)
{
    PyObject *oobj, *dobj;
    int ok = loops ? PyArg_ParseTuple(args, fmt, cap, &oobj, &dobj, loops)
                   : PyArg_ParseTuple(args, fmt, cap, &oobj, &dobj);
    if (!ok) {
        return -1;
    }
    *o = as_rows3(oobj, NPY_FLOAT64, "origins");
    if (!*o) {
        return -1;
    }
    *d = as_rows3(dobj, NPY_FLOAT64, "directions");
    if (!*d) {
        Py_DECREF(*o);
        return -1;
    }
    if (PyArray_DIM(*o, 0) != PyArray_DIM(*d, 0)) {
        PyErr_SetString(PyExc_ValueError, "origins and directions need the same number of rays");
        Py_DECREF(*o);
        Py_DECREF(*d);
        return -1;
    }
    return 0;
}

static PyObject *py_intersect(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *cap;
    PyArrayObject *o, *d;
    if (parse_rays(args, "OOO", &cap, &o, &d, NULL) < 0) {
        return NULL;
    }
    gc_grid *g = get_grid(cap);
    npy_intp n = PyArray_DIM(o, 0);
    PyArrayObject *t = g ? (PyArrayObject *)PyArray_SimpleNew(1, &n, NPY_FLOAT64) : NULL;
    PyArrayObject *pr = t ? (PyArrayObject *)PyArray_SimpleNew(1, &n, NPY_INT32) : NULL;
    if (!pr) {
        Py_DECREF(o), Py_DECREF(d), Py_XDECREF(t);
        return NULL;
    }
    char err[GC_ERROR_LEN] = "";
    gc_status st;
    Py_BEGIN_ALLOW_THREADS st =
        gc_intersect(g, (int64_t)n, PyArray_DATA(o), PyArray_DATA(d), PyArray_DATA(t), PyArray_DATA(pr), err);
    Py_END_ALLOW_THREADS Py_DECREF(o);
    Py_DECREF(d);
    if (st != GC_OK) {
        Py_DECREF(t), Py_DECREF(pr);
        return raise_status(st, err);
    }
    return Py_BuildValue("(NN)", t, pr);
}

static PyObject *py_count(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *cap;
    PyArrayObject *o, *d;
    if (parse_rays(args, "OOO", &cap, &o, &d, NULL) < 0) {
        return NULL;
    }
    gc_grid *g = get_grid(cap);
    npy_intp n = PyArray_DIM(o, 0);
    enum { N_OUT = 7 }; /* t, prim, steps, tests, subgrids, visits, changes */
    PyArrayObject *out[N_OUT] = {NULL};
    const int types[N_OUT] = {NPY_FLOAT64, NPY_INT32, NPY_UINT32, NPY_UINT32, NPY_UINT32, NPY_UINT32, NPY_UINT32};
    int ok = g != NULL;
    for (int i = 0; i < N_OUT && ok; ++i) {
        out[i] = (PyArrayObject *)PyArray_SimpleNew(1, &n, types[i]);
        ok = out[i] != NULL;
    }
    if (!ok) {
        Py_DECREF(o), Py_DECREF(d);
        for (int i = 0; i < N_OUT; ++i) {
            Py_XDECREF(out[i]);
        }
        return NULL;
    }
    char err[GC_ERROR_LEN] = "";
    gc_status st;
    Py_BEGIN_ALLOW_THREADS st = gc_count(g, (int64_t)n, PyArray_DATA(o), PyArray_DATA(d),
                                         PyArray_DATA(out[0]), PyArray_DATA(out[1]),
                                         PyArray_DATA(out[2]), PyArray_DATA(out[3]),
                                         PyArray_DATA(out[4]), PyArray_DATA(out[5]),
                                         PyArray_DATA(out[6]), err);
    Py_END_ALLOW_THREADS Py_DECREF(o);
    Py_DECREF(d);
    if (st != GC_OK) {
        for (int i = 0; i < N_OUT; ++i) {
            Py_DECREF(out[i]);
        }
        return raise_status(st, err);
    }
    return Py_BuildValue("(NNNNNNN)", out[0], out[1], out[2], out[3], out[4], out[5], out[6]);
}

static PyObject *py_bench(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *cap;
    PyArrayObject *o, *d;
    long long loops;
    if (parse_rays(args, "OOOL", &cap, &o, &d, &loops) < 0) {
        return NULL;
    }
    gc_grid *g = get_grid(cap);
    if (!g) {
        Py_DECREF(o), Py_DECREF(d);
        return NULL;
    }
    npy_intp n = PyArray_DIM(o, 0);
    int64_t elapsed = 0;
    double checksum = 0.0;
    char err[GC_ERROR_LEN] = "";
    gc_status st;
    Py_BEGIN_ALLOW_THREADS st = gc_bench_intersect(g, (int64_t)n, PyArray_DATA(o), PyArray_DATA(d),
                                                   (int64_t)loops, &elapsed, &checksum, err);
    Py_END_ALLOW_THREADS Py_DECREF(o);
    Py_DECREF(d);
    if (st != GC_OK) {
        return raise_status(st, err);
    }
    return Py_BuildValue("(Ld)", (long long)elapsed, checksum);
}

static PyObject *py_brute_force(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *vobj, *fobj, *oobj, *dobj;
    int intersector;
    if (!PyArg_ParseTuple(args, "OOiOO", &vobj, &fobj, &intersector, &oobj, &dobj)) {
        return NULL;
    }
    PyArrayObject *v = as_rows3(vobj, NPY_FLOAT64, "vertices");
    PyArrayObject *f = v ? as_rows3(fobj, NPY_INT64, "faces") : NULL;
    PyArrayObject *o = f ? as_rows3(oobj, NPY_FLOAT64, "origins") : NULL;
    PyArrayObject *d = o ? as_rows3(dobj, NPY_FLOAT64, "directions") : NULL;
    if (!d) {
        Py_XDECREF(v), Py_XDECREF(f), Py_XDECREF(o);
        return NULL;
    }
    if (PyArray_DIM(o, 0) != PyArray_DIM(d, 0)) {
        PyErr_SetString(PyExc_ValueError, "origins and directions need the same number of rays");
        Py_DECREF(v), Py_DECREF(f), Py_DECREF(o), Py_DECREF(d);
        return NULL;
    }
    npy_intp n = PyArray_DIM(o, 0);
    PyArrayObject *t = (PyArrayObject *)PyArray_SimpleNew(1, &n, NPY_FLOAT64);
    PyArrayObject *pr = t ? (PyArrayObject *)PyArray_SimpleNew(1, &n, NPY_INT32) : NULL;
    if (!pr) {
        Py_DECREF(v), Py_DECREF(f), Py_DECREF(o), Py_DECREF(d), Py_XDECREF(t);
        return NULL;
    }
    gc_mesh mesh = {(const double *)PyArray_DATA(v), (int64_t)PyArray_DIM(v, 0),
                    (const int64_t *)PyArray_DATA(f), (int64_t)PyArray_DIM(f, 0)};
    char err[GC_ERROR_LEN] = "";
    gc_status st;
    Py_BEGIN_ALLOW_THREADS st = gc_brute_force(&mesh, (gc_intersector)intersector, (int64_t)n,
                                               PyArray_DATA(o), PyArray_DATA(d), PyArray_DATA(t),
                                               PyArray_DATA(pr), err);
    Py_END_ALLOW_THREADS Py_DECREF(v);
    Py_DECREF(f), Py_DECREF(o), Py_DECREF(d);
    if (st != GC_OK) {
        Py_DECREF(t), Py_DECREF(pr);
        return raise_status(st, err);
    }
    return Py_BuildValue("(NN)", t, pr);
}

static PyObject *py_triangle_box_overlap(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *objs[5];
    if (!PyArg_ParseTuple(args, "OOOOO", &objs[0], &objs[1], &objs[2], &objs[3], &objs[4])) {
        return NULL;
    }
    double v[5][3];
    for (int i = 0; i < 5; ++i) {
        if (read_doubles(objs[i], v[i], 3, "a 3-vector") < 0) {
            return NULL;
        }
    }
    return PyBool_FromLong(gc_triangle_box_overlap(v[0], v[1], v[2], v[3], v[4]));
}

/* triangle_box_overlap_many(corners (P, 9), lo (P, 3), hi (P, 3)) -> (P,) bool: pair p tests
 * the triangle corners[p] against the box [lo[p], hi[p]] (models.nested's vectorised test). */
static PyObject *py_triangle_box_overlap_many(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *tobj, *lobj, *hobj;
    if (!PyArg_ParseTuple(args, "OOO", &tobj, &lobj, &hobj)) {
        return NULL;
    }
    PyArrayObject *t = (PyArrayObject *)PyArray_FROM_OTF(tobj, NPY_FLOAT64, NPY_ARRAY_IN_ARRAY);
    PyArrayObject *lo = t ? as_rows3(lobj, NPY_FLOAT64, "lo") : NULL;
    PyArrayObject *hi = lo ? as_rows3(hobj, NPY_FLOAT64, "hi") : NULL;
    if (!hi) {
        Py_XDECREF(t), Py_XDECREF(lo);
        return NULL;
    }
    npy_intp n = PyArray_DIM(lo, 0);
    if (PyArray_NDIM(t) != 2 || PyArray_DIM(t, 1) != 9 || PyArray_DIM(t, 0) != n || PyArray_DIM(hi, 0) != n) {
        PyErr_SetString(PyExc_ValueError, "corners must have shape (n, 9) and lo, hi shape (n, 3)");
        Py_DECREF(t), Py_DECREF(lo), Py_DECREF(hi);
        return NULL;
    }
    PyArrayObject *out = (PyArrayObject *)PyArray_SimpleNew(1, &n, NPY_BOOL);
    if (out) {
        const double *tv = PyArray_DATA(t), *l = PyArray_DATA(lo), *h = PyArray_DATA(hi);
        npy_bool *o = PyArray_DATA(out);
        Py_BEGIN_ALLOW_THREADS
        for (npy_intp p = 0; p < n; ++p) {
            const double *c = tv + 9 * p;
            o[p] = (npy_bool)gc_triangle_box_overlap(c, c + 3, c + 6, l + 3 * p, h + 3 * p);
        }
        Py_END_ALLOW_THREADS
    }
    Py_DECREF(t), Py_DECREF(lo), Py_DECREF(hi);
    return (PyObject *)out;
}

static PyObject *py_mesh_sums(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *vobj, *fobj;
    long long stride;
    if (!PyArg_ParseTuple(args, "OOL", &vobj, &fobj, &stride)) {
        return NULL;
    }
    if (stride < 1) {
        PyErr_SetString(PyExc_ValueError, "stride must be >= 1");
        return NULL;
    }
    PyArrayObject *v = as_rows3(vobj, NPY_FLOAT64, "vertices");
    PyArrayObject *f = v ? as_rows3(fobj, NPY_INT64, "faces") : NULL;
    if (!f) {
        Py_XDECREF(v);
        return NULL;
    }
    npy_intp nf = PyArray_DIM(f, 0);
    npy_intp room = nf ? (nf - 1) / (npy_intp)stride + 1 : 0;
    PyArrayObject *ar = (PyArrayObject *)PyArray_SimpleNew(1, &room, NPY_FLOAT64);
    if (!ar) {
        Py_DECREF(v), Py_DECREF(f);
        return NULL;
    }
    gc_mesh mesh = {(const double *)PyArray_DATA(v), (int64_t)PyArray_DIM(v, 0),
                    (const int64_t *)PyArray_DATA(f), (int64_t)nf};
    gc_mesh_sums sums;
    int64_t n_ar = 0;
    char err[GC_ERROR_LEN] = "";
    gc_status st;
    Py_BEGIN_ALLOW_THREADS st = gc_mesh_sums_compute(&mesh, (int64_t)stride, PyArray_DATA(ar), &n_ar,
                                                     &sums, err);
    Py_END_ALLOW_THREADS Py_DECREF(v);
    Py_DECREF(f);
    if (st != GC_OK) {
        Py_DECREF(ar);
        return raise_status(st, err);
    }
    PyObject *sample = PySequence_GetSlice((PyObject *)ar, 0, (Py_ssize_t)n_ar);
    Py_DECREF(ar);
    if (!sample) {
        return NULL;
    }
#define TRIPLE(x) (x)[0], (x)[1], (x)[2]
    return Py_BuildValue("{s:(ddd),s:(ddd),s:(ddd),s:(ddd),s:(ddd),s:(ddd),s:d,s:d,s:d,s:L,s:N}",
                         "box_lo", TRIPLE(sums.box_lo), "box_hi", TRIPLE(sums.box_hi), "e1", TRIPLE(sums.e1),
                         "e2", TRIPLE(sums.e2), "perimeters", TRIPLE(sums.perimeters), "pair",
                         TRIPLE(sums.pair), "triple", sums.triple, "area", sums.area, "vol6", sums.vol6,
                         "n_good", (long long)sums.n_good, "aspect_sample", sample);
#undef TRIPLE
}

static PyObject *py_mesh_topology(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *vobj, *fobj;
    if (!PyArg_ParseTuple(args, "OO", &vobj, &fobj)) {
        return NULL;
    }
    PyArrayObject *v = as_rows3(vobj, NPY_FLOAT64, "vertices");
    PyArrayObject *f = v ? as_rows3(fobj, NPY_INT64, "faces") : NULL;
    if (!f) {
        Py_XDECREF(v);
        return NULL;
    }
    gc_mesh mesh = {(const double *)PyArray_DATA(v), (int64_t)PyArray_DIM(v, 0),
                    (const int64_t *)PyArray_DATA(f), (int64_t)PyArray_DIM(f, 0)};
    int wt = 0;
    int64_t positions = 0;
    char err[GC_ERROR_LEN] = "";
    gc_status st;
    Py_BEGIN_ALLOW_THREADS st = gc_mesh_topology(&mesh, &wt, &positions, err);
    Py_END_ALLOW_THREADS Py_DECREF(v);
    Py_DECREF(f);
    if (st != GC_OK) {
        return raise_status(st, err);
    }
    return Py_BuildValue("(NL)", PyBool_FromLong(wt), (long long)positions);
}

static PyObject *py_mesh_watertight(PyObject *self, PyObject *args)
{
    PyObject *both = py_mesh_topology(self, args);
    if (!both) {
        return NULL;
    }
    PyObject *wt = PyTuple_GET_ITEM(both, 0);
    Py_INCREF(wt);
    Py_DECREF(both);
    return wt;
}

static PyObject *py_timer_resolution_ns(PyObject *self, PyObject *args)
{
    (void)self;
    (void)args;
    return PyLong_FromLongLong((long long)gc_timer_resolution_ns());
}

static PyObject *py_traverse_isa(PyObject *self, PyObject *args)
{
    (void)self;
    (void)args;
    return PyUnicode_FromString(gc_traverse_isa());
}

static PyObject *py_set_traverse_isa(PyObject *self, PyObject *args)
{
    (void)self;
    const char *isa;
    if (!PyArg_ParseTuple(args, "s", &isa)) {
        return NULL;
    }
    char err[GC_ERROR_LEN] = "";
    gc_status st = gc_traverse_set_isa(isa, err);
    if (st != GC_OK) {
        return raise_status(st, err);
    }
    return PyUnicode_FromString(gc_traverse_isa());
}

static PyMethodDef methods[] = {
    {"build", (PyCFunction)(void (*)(void))py_build, METH_VARARGS | METH_KEYWORDS,
     "build(vertices, faces, resolution, ...) -> grid capsule"},
    {"info", py_info, METH_VARARGS, "info(grid) -> dict"},
    {"top_counts", py_top_counts, METH_VARARGS, "top_counts(grid) -> (nz, ny, nx) int64"},
    {"intersect", py_intersect, METH_VARARGS, "intersect(grid, origins, directions) -> (t, prim)"},
    {"count", py_count, METH_VARARGS,
     "count(grid, origins, directions) -> (t, prim, steps, tests, subgrids, visits, changes)"},
    {"mesh_topology", py_mesh_topology, METH_VARARGS,
     "mesh_topology(vertices, faces) -> (watertight, distinct positions)"},
    {"bench", py_bench, METH_VARARGS,
     "bench(grid, origins, directions, loops) -> (elapsed_ns, checksum)"},
    {"brute_force", py_brute_force, METH_VARARGS,
     "brute_force(vertices, faces, intersector, origins, directions) -> (t, prim)"},
    {"triangle_box_overlap", py_triangle_box_overlap, METH_VARARGS,
     "triangle_box_overlap(v0, v1, v2, lo, hi) -> bool"},
    {"triangle_box_overlap_many", py_triangle_box_overlap_many, METH_VARARGS,
     "triangle_box_overlap_many(corners (n, 9), lo (n, 3), hi (n, 3)) -> (n,) bool"},
    {"mesh_sums", py_mesh_sums, METH_VARARGS,
     "mesh_sums(vertices, faces, stride) -> dict of the scene sums (models.stats)"},
    {"mesh_watertight", py_mesh_watertight, METH_VARARGS, "mesh_watertight(vertices, faces) -> bool"},
    {"timer_resolution_ns", py_timer_resolution_ns, METH_NOARGS, "clock_getres of CLOCK_MONOTONIC"},
    {"traverse_isa", py_traverse_isa, METH_NOARGS,
     "traverse_isa() -> 'avx2' | 'sse2' | 'scalar': the timed twin's sign stage"},
    {"set_traverse_isa", py_set_traverse_isa, METH_VARARGS,
     "set_traverse_isa('sse2' | 'avx2' | 'auto') -> the instruction set now in use"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_kernels",
                                    "gridcal's C grid kernels (see kernels/gridcal.h).", -1, methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__kernels(void)
{
    import_array();
    PyObject *m = PyModule_Create(&module);
    if (!m) {
        return NULL;
    }
    PyModule_AddStringConstant(m, "CFLAGS", GRIDCAL_CFLAGS);
    PyModule_AddStringConstant(m, "VERSION", GC_VERSION_STRING);
    PyModule_AddIntConstant(m, "MAX_LEVELS", GC_MAX_LEVELS);
    PyModule_AddIntConstant(m, "MAX_BUILD_THREADS", GC_MAX_THREADS);
    PyModule_AddIntConstant(m, "MOLLER_TRUMBORE", GC_MOLLER_TRUMBORE);
    PyModule_AddIntConstant(m, "WATERTIGHT", GC_WATERTIGHT);
    PyModule_AddIntConstant(m, "INSERT_EXACT", GC_INSERT_EXACT);
    PyModule_AddIntConstant(m, "INSERT_BOUNDS", GC_INSERT_BOUNDS);
    PyModule_AddObject(m, "MAX_CELLS", PyLong_FromUnsignedLongLong(GC_MAX_CELLS));
    PyModule_AddObject(m, "DEFAULT_MEMORY_LIMIT_BYTES",
                       PyLong_FromUnsignedLongLong(GC_DEFAULT_MEMORY_LIMIT_BYTES));
    return m;
}
