"""`calibrate export`: the C header compiles cleanly, its functions return the Python
predictions bit for bit, host text cannot escape its comment, and bad inputs fail cleanly.

The compile tests need gcc and g++ and skip, saying so, without them.  Every C check runs
through one compiled driver program fed all seeded cases on stdin.
"""

from __future__ import annotations

import json
import math
import os
import random
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from calibrate import calfile
from calibrate.cli import main
from calibrate.export import FUNCTIONS, header_text, sanitize_comment
from models import portable as P
from models.closed_forms import cells_to_resolution, l_level_cells
from models.general import optimal_cell_size
from models.nested import MAX_LEVELS
from models.stats import grid_box, scene_class

#: The sample columns of a four-constant calibration (no memory term).
FOUR_CONSTANT_COLUMNS = ["t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "extra_scatter"]

GCC = shutil.which("gcc")
GXX = shutil.which("g++")
needs_gcc = pytest.mark.skipif(GCC is None, reason="gcc is not installed: the header's C99 checks need it")
needs_gxx = pytest.mark.skipif(GXX is None, reason="g++ is not installed: the header's C++17 check needs it")
WARNINGS = ["-Wall", "-Wextra", "-Werror", "-pedantic", "-Wshadow", "-Wconversion", "-Wdouble-promotion"]
#: How the project builds C (setup.py): no fused multiply-add, no fast math.
FP_FLAGS = ["-O2", "-ffp-contract=off", "-fno-fast-math"]
#: Planted calibration constants (ns) and ratio of the test calibration.
PLANTED = dict(t_setup_ns=58.76, t_step_ns=22.06, t_int_ns=20.44, t_sub_ns=43.84, ratio=0.9263)
HOSTILE_CPUS = [
    "*/ #error x",
    "AMD EPYC\n#error injected on a new line",
    "Intel(R) Xeon(R) \\",  # a backslash at the end of a line would splice the next line
    "weird ??/\n#error trigraph splice",
    "Caf\u00e9 \u2603 CPU \u202e*/",
    "/* nested */ */ /* #define GRIDCAL_RATIO 0",
    "\r\n*/\r\n#error crlf",
]
N_CASES_PER_KIND = 120


def make_calibration(cpu="Test CPU @ 3.0GHz", **fp) -> dict:
    consts = {}
    for key, med in PLANTED.items():
        consts[key] = dict(median=med, ci68=[0.9 * med, 1.1 * med], ci95=[0.8 * med, 1.2 * med])
    row = [PLANTED["t_setup_ns"], PLANTED["t_step_ns"], PLANTED["t_int_ns"], PLANTED["t_sub_ns"], 0.1]
    cal = dict(schema_version=calfile.SCHEMA_VERSION,
               fingerprint=dict(cpu_model=cpu, date_utc="2026-11-22T06:00:00+00:00",
                                kernel_build="gcc 12; -std=c99 -O2 -ffp-contract=off -fno-fast-math",
                                kernel_isa="avx2", **fp),
               constants=consts,
               samples=dict(columns=FOUR_CONSTANT_COLUMNS, values=[row, row]),
               diagnostics=dict(converged=True), measurements=[], meta={})
    return calfile.validate(cal)


def write_cal(path: Path, cal: dict) -> Path:
    path.write_text(json.dumps(cal))
    return path


def compile_c(tmp: Path, header: str, main_c: str, *, cxx=False, name="prog") -> Path:
    (tmp / "grid_tuning.h").write_text(header)
    src = tmp / (name + (".cpp" if cxx else ".c"))
    src.write_text(main_c)
    exe = tmp / name
    cmd = ([GXX, "-std=c++17"] if cxx else [GCC, "-std=c99"]) + WARNINGS + FP_FLAGS + [
        "-I", str(tmp), str(src), "-o", str(exe), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return exe


# --- portable arithmetic against the library and the existing models --------------------------


@pytest.mark.parametrize("i", range(4))
def test_portable_log_exp_pow_match_libm(i):
    rng = random.Random(i)
    for _ in range(2000):
        x = math.exp(rng.uniform(-700, 700))
        assert P.plog(x) == pytest.approx(math.log(x), rel=1e-15, abs=1e-15)
        y = 1.0 + rng.uniform(-1e-3, 1e-3)  # near 1, where log is small
        assert P.plog(y) == pytest.approx(math.log(y), rel=1e-14)
        t = rng.uniform(-740, 709)
        assert P.pexp(t) == pytest.approx(math.exp(t), rel=2e-15)
        b, e = math.exp(rng.uniform(-20, 20)), rng.uniform(-3, 3)
        assert P.ppow(b, e) == pytest.approx(b ** e, rel=1e-13)
    assert P.plog(0.0) == -math.inf and P.plog(math.inf) == math.inf
    assert P.pexp(1000.0) == math.inf and P.pexp(-1000.0) == 0.0


def test_round_half_even():
    assert [P.round_half_even(x) for x in (0.5, 1.5, 2.5, 2.4999999, 2.5000001, 0.0, 7.0)] == [0, 2, 2, 2, 3, 0, 7]


@pytest.mark.parametrize("i", range(4))
def test_portable_forms_match_the_closed_forms_and_the_cubic(i):
    rng = random.Random(100 + i)
    for _ in range(40):
        n, r, k = 10 ** rng.uniform(0, 9), 10 ** rng.uniform(-2, 2), 10 ** rng.uniform(-1, 1.5)
        for L in range(1, 4):
            for kind in ("points", "lines"):
                want = [float(c) for c in l_level_cells(n, r, L, k, kind=kind)]
                assert P.paper_level_cells(n, r, L, k, kind) == pytest.approx(want, rel=1e-12)
        ext = [10 ** rng.uniform(-3, 3) for _ in range(3)]
        e1 = n * sum(ext) * rng.uniform(0, 0.1)
        stats = _Stats(n, ext, e1)
        h = optimal_cell_size(stats, 1.0, r)
        assert P.general_cells(n, e1, ext, r) == pytest.approx(stats.volume / h ** 3, rel=1e-9)


class _Stats:
    """The few SceneStats fields the cubic needs."""

    def __init__(self, n, ext, e1):
        self.n_triangles, self.extent, self.e1 = n, np.asarray(ext), e1
        self.volume = ext[0] * ext[1] * ext[2]
        self.perimeters = np.zeros(3)
        self.bbox_triple_sum = 0.0


def test_general_cells_without_e1_is_the_points_law():
    for n in (1.0, 1e3, 1e9):
        assert P.general_cells(n, 0.0, [1.0, 2.0, 3.0], 0.9) == pytest.approx(2 * n * 0.9, rel=1e-14)


def test_resolution_for_cells_is_cells_to_resolution_and_the_talk_rule():
    assert cells_to_resolution(8000, [1, 2, 4]) == P.resolution_for_cells(8000, [1, 2, 4]) == (10, 20, 40)
    assert P.resolution_for_cells(math.inf, [1, 1, 1]) == (406, 406, 406)  # 406^3 <= 2^26 < 407^3
    assert P.resolution_for_cells(1e30, [1, 1e-9, 1]) == (4096, 1, 4096)


def test_predict_paper_fidelity_uses_the_portable_resolutions():
    from calibrate._grid import Scene
    from calibrate.predict import paper_plan, resolve_constants

    k = resolve_constants(ratio=0.9263)
    for name in ("cylinder196", "cylinder1996", "scattered-compact"):
        scene = Scene.builtin(name)
        stats = scene.stats
        cls, _ = scene_class(stats)
        tri = scene.vertices[scene.faces]
        lo, hi = tri.min(axis=(0, 1)), tri.max(axis=(0, 1))
        for L in range(1, MAX_LEVELS + 1):
            plan, _ = paper_plan(stats, cls, k, str(L))
            want = P.paper_resolutions(stats.n_triangles, lo, hi, 0.9263, L, cls, stats.k)
            assert [tuple(lv["resolution"]) for lv in plan["levels"]] == want


def test_constants_mirror_the_models():
    import models.closed_forms as CF
    import models.general as G

    assert P.MAX_LEVELS == MAX_LEVELS and P.CUBIC_NEWTON_ITERATIONS == G.CUBIC_NEWTON_ITERATIONS
    assert (P.MAX_CELLS_PER_AXIS, P.MAX_TOTAL_CELLS, P.K_CUBE) == (CF.MAX_CELLS_PER_AXIS, CF.MAX_TOTAL_CELLS,
                                                                  CF.K_CUBE)


# --- seeded cases for the C mirror ------------------------------------------------------------


def _box(rng):
    """A scene box: random scale 1e-100..1e100, offset, and often flat or a single point."""
    scale = 10 ** rng.uniform(-100, 100)
    centre = [rng.uniform(-1, 1) * scale * rng.choice((0, 1, 1e3)) for _ in range(3)]
    ext = [scale * 10 ** rng.uniform(-2, 0) for _ in range(3)]
    shape = rng.random()
    if shape < 0.15:
        ext[rng.randrange(3)] = 0.0  # flat
    elif shape < 0.25:
        ext = [0.0, 0.0, ext[0]] if rng.random() < 0.5 else [0.0, 0.0, 0.0]  # a segment or a point
    lo = [c - 0.5 * e for c, e in zip(centre, ext, strict=True)]
    hi = [c + 0.5 * e for c, e in zip(centre, ext, strict=True)]
    return lo, hi


def _n(rng):
    return rng.choice([0.0, 1.0, 1.0, 2.0, 1e9, 2.5e9, 1e12, 1e18, float(rng.randrange(1, 1000)),
                       float(round(10 ** rng.uniform(0, 9)))])


def _r(rng):
    return rng.choice([0.9263, 10 ** rng.uniform(-2, 2), 10 ** rng.uniform(-2, 2)])


def _case(kind, i):
    """One seeded case: (line for the C driver, expected output line from models.portable)."""
    rng = random.Random(f"{kind}-{i}")
    h = lambda x: float(x).hex()  # noqa: E731  (exact: C reads hex floats)
    if kind == "P":
        lo, hi = _box(rng)
        n, r, levels = _n(rng), _r(rng), rng.randint(1, 3)
        cls = rng.randrange(3)
        k = rng.choice([6.0, 10 ** rng.uniform(-4, 2), math.nan, math.inf, 0.0, -1.0])
        if i % 17 == 5:  # bad inputs: NaN corner, hi < lo, r <= 0
            lo[0], r = (math.nan, r) if i % 3 == 0 else ((hi[0] + 1.0, r) if i % 3 == 1 else (lo[0], 0.0))
        args = [cls, levels, h(n), *map(h, lo), *map(h, hi), h(k), h(r)]
        try:
            res = P.paper_resolutions(n, lo, hi, r, levels, P.SCENE_CLASSES[cls], k)
            want = " ".join(" ".join(f"0 {x} {y} {z}" for x, y, z in [lv]) for lv in res)
        except ValueError:
            want = " ".join(["-1 1 1 1"] * levels)
    elif kind == "G":
        lo, hi = _box(rng)
        n, r = _n(rng), _r(rng)
        ext_guess = max(hi[j] - lo[j] for j in range(3)) or 1.0
        e1 = rng.choice([0.0, n * ext_guess * 10 ** rng.uniform(-3, 0.5), 1e-3 * ext_guess])
        if i % 19 == 7:
            e1 = rng.choice([-1.0, math.nan, math.inf])
        args = [h(n), h(e1), *map(h, lo), *map(h, hi), h(r)]
        try:
            x, y, z = P.general_resolution(n, e1, lo, hi, r)
            want = f"0 {x} {y} {z}"
        except ValueError:
            want = "-1 1 1 1"
        try:  # the continuous optimum itself, bit for bit
            want += " 0 " + h(P.general_cells(n, e1, P.grid_extent(lo, hi), r))
        except ValueError:
            want += " -1"
    elif kind == "C":
        cells = rng.choice([10 ** rng.uniform(-5, 30), math.inf, 1.0, 0.5, 2.0 ** 26, 2.0 ** 26 + 1, 0.0])
        ext = [10 ** rng.uniform(-150, 150) for _ in range(3)]
        if rng.random() < 0.3:
            ext[rng.randrange(3)] *= 1e-12  # extreme aspect: clamps per axis and in total
        args = [h(cells), *map(h, ext)]
        try:
            x, y, z = P.resolution_for_cells(cells, ext)
            want = f"0 {x} {y} {z}"
        except ValueError:
            want = "-1 1 1 1"
    elif kind == "E":
        lo, hi = _box(rng)
        if i % 13 == 3:
            lo, hi = [-1e308, 0.0, 0.0], [1e308, 1.0, 1.0]  # the extent overflows
        args = [*map(h, lo), *map(h, hi)]
        try:
            ext = P.grid_extent(lo, hi)
            ref = grid_box(lo, hi)
            assert [float(v) for v in ref[1] - ref[0]] == list(ext)  # bit for bit the models' grid box
            want = "0 " + " ".join(h(v) for v in ext)
        except ValueError:
            want = "-1"
    elif kind == "L":
        n, r, levels = 10 ** rng.uniform(0, 12), _r(rng), rng.randint(1, 3)
        k, lines = 10 ** rng.uniform(-3, 2), rng.randrange(2)
        args = [h(n), h(r), levels, h(k), lines]
        cells = P.paper_level_cells(n, r, levels, k, "lines" if lines else "points")
        want = "0 " + " ".join(h(c) for c in cells)
    elif kind == "X":
        x = rng.choice([10 ** rng.uniform(-300, 300), 1.0 + rng.uniform(-1e-6, 1e-6), rng.uniform(0, 2), 0.0,
                        math.inf, 5e-324, 2.0 ** rng.randrange(-1074, 1024)])
        t = rng.choice([rng.uniform(-750, 712), rng.uniform(-1, 1), 0.0])
        y = rng.choice([1.0 / 3.0, 1.5, 0.6, rng.uniform(-3, 3)])
        args = [h(x), h(t), h(y)]
        want = " ".join(h(v) for v in (P.plog(x), P.pexp(t), P.ppow(x, y), P.round_half_even(abs(t) * 1e3)))
    elif kind == "S":
        n = float(rng.randrange(1, 10 ** 6))
        nd = rng.choice([0.0, float(rng.randrange(0, int(n) + 1)), math.floor(n / 2), math.floor(n / 2) + 1])
        med, p95 = rng.choice([1.2, 2.0, 4.0, 5.0, 10.0, 30.0, math.inf]), rng.choice([3.0, 16.0, 17.0, math.inf])
        args = [h(n), h(nd), h(med), h(p95)]
        stats = type("S", (), dict(n_triangles=int(n), n_degenerate=int(nd), aspect_median=med, aspect_p95=p95))
        want = str(P.SCENE_CLASSES.index(scene_class(stats)[0]))
        assert int(want) == P.scene_class_code(n, nd, med, p95)
    else:  # "W": the wrappers with the header's own GRIDCAL_RATIO
        lo, hi = _box(rng)
        n = _n(rng)
        e1 = n * max(hi[j] - lo[j] for j in range(3)) * rng.uniform(0, 2)
        k = rng.choice([6.0, 2.5])
        r = PLANTED["ratio"]
        args = [h(n), h(e1), *map(h, lo), *map(h, hi), h(k)]
        outs = []
        for cls in P.SCENE_CLASSES:
            outs.append(P.paper_resolutions(n, lo, hi, r, 1, cls, P.K_CUBE)[0])
        outs.append(P.general_resolution(n, e1, lo, hi, r))
        outs += P.paper_resolutions(n, lo, hi, r, 2, "compact", k)
        outs += P.paper_resolutions(n, lo, hi, r, 3, "long-skinny", k)
        want = " ".join(f"{x} {y} {z}" for x, y, z in outs)
    return f"{kind} " + " ".join(str(a) for a in args), want


DRIVER = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "grid_tuning.h"

static double rd(void) { char b[64]; if (scanf("%63s", b) != 1) exit(3); return strtod(b, NULL); }
static int ri(void) { int v; if (scanf("%d", &v) != 1) exit(3); return v; }

int main(void)
{
    char kind[4];
    while (scanf("%3s", kind) == 1) {
        double lo[3], hi[3], ext[3], cells[GRIDCAL_MAX_LEVELS], n, r, k, e1, c;
        int out[3], i, rc, cls, levels, level, lines;
        if (strcmp(kind, "P") == 0) {
            cls = ri(); levels = ri(); n = rd();
            for (i = 0; i < 3; i++) lo[i] = rd();
            for (i = 0; i < 3; i++) hi[i] = rd();
            k = rd(); r = rd();
            for (level = 1; level <= levels; level++) {
                rc = gridcal_paper_resolution(cls, levels, level, n, lo, hi, k, r, out);
                printf("%s%d %d %d %d", level > 1 ? " " : "", rc, out[0], out[1], out[2]);
            }
        } else if (strcmp(kind, "G") == 0) {
            n = rd(); e1 = rd();
            for (i = 0; i < 3; i++) lo[i] = rd();
            for (i = 0; i < 3; i++) hi[i] = rd();
            r = rd();
            rc = gridcal_general_resolution_r(n, e1, lo, hi, r, out);
            printf("%d %d %d %d", rc, out[0], out[1], out[2]);
            if (gridcal_grid_extent(lo, hi, ext) != 0 || gridcal_general_cells(n, e1, ext, r, &c) != 0)
                printf(" -1");
            else
                printf(" 0 %a", c);
        } else if (strcmp(kind, "C") == 0) {
            c = rd();
            for (i = 0; i < 3; i++) ext[i] = rd();
            rc = gridcal_resolution_for_cells(c, ext, out);
            printf("%d %d %d %d", rc, out[0], out[1], out[2]);
        } else if (strcmp(kind, "E") == 0) {
            for (i = 0; i < 3; i++) lo[i] = rd();
            for (i = 0; i < 3; i++) hi[i] = rd();
            rc = gridcal_grid_extent(lo, hi, ext);
            if (rc == 0) printf("0 %a %a %a", ext[0], ext[1], ext[2]); else printf("%d", rc);
        } else if (strcmp(kind, "L") == 0) {
            n = rd(); r = rd(); levels = ri(); k = rd(); lines = ri();
            rc = gridcal_paper_level_cells(n, r, levels, k, lines, cells);
            printf("%d", rc);
            for (i = 0; i < levels; i++) printf(" %a", cells[i]);
        } else if (strcmp(kind, "X") == 0) {
            double x = rd(), t = rd(), y = rd();
            printf("%a %a %a %a", gridcal_log_(x), gridcal_exp_(t), gridcal_pow_(x, y), gridcal_round_(fabs(t) * 1e3));
        } else if (strcmp(kind, "S") == 0) {
            double nt = rd(), nd = rd(), med = rd(), p95 = rd();
            printf("%d", gridcal_scene_class(nt, nd, med, p95));
        } else if (strcmp(kind, "W") == 0) {
            n = rd(); e1 = rd();
            for (i = 0; i < 3; i++) lo[i] = rd();
            for (i = 0; i < 3; i++) hi[i] = rd();
            k = rd();
            gridcal_compact(n, lo, hi, out); printf("%d %d %d", out[0], out[1], out[2]);
            gridcal_long_skinny(n, lo, hi, out); printf(" %d %d %d", out[0], out[1], out[2]);
            gridcal_mixed(n, lo, hi, out); printf(" %d %d %d", out[0], out[1], out[2]);
            gridcal_general(n, e1, lo, hi, out); printf(" %d %d %d", out[0], out[1], out[2]);
            for (level = 1; level <= 2; level++) {
                gridcal_nested(GRIDCAL_COMPACT, 2, level, n, lo, hi, k, out);
                printf(" %d %d %d", out[0], out[1], out[2]);
            }
            for (level = 1; level <= 3; level++) {
                gridcal_nested(GRIDCAL_LONG_SKINNY, 3, level, n, lo, hi, k, out);
                printf(" %d %d %d", out[0], out[1], out[2]);
            }
        } else {
            return 4;
        }
        printf("\n");
    }
    return 0;
}
"""


def _hex_to_float_line(line: str) -> list:
    """Parse %a output (glibc and Python spell hex floats differently) into floats."""
    return [float.fromhex(t) if "0x" in t or "inf" in t else int(t) for t in line.split()]


@needs_gcc
def test_header_functions_equal_the_python_predictions(tmp_path):
    exe = compile_c(tmp_path, header_text(make_calibration()), DRIVER)
    cases = [_case(kind, i) for kind in "PGCELXSW" for i in range(N_CASES_PER_KIND)]
    proc = subprocess.run([str(exe)], input="\n".join(c[0] for c in cases) + "\n", capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    got = proc.stdout.splitlines()
    assert len(got) == len(cases)
    mismatches = [(line, want, have) for (line, want), have in zip(cases, got, strict=True)
                  if _hex_to_float_line(want) != _hex_to_float_line(have)]
    assert not mismatches, f"{len(mismatches)} of {len(cases)} differ, first: {mismatches[:3]}"
    # the cases reach the hard corners: clamps, flat boxes, errors, one-cell grids
    wants = " ".join(w for _, w in cases)
    assert "4096" in wants and "-1 1 1 1" in wants and "0 1 1 1" in wants


# --- compiling ------------------------------------------------------------------------------------

SMOKE = """
#include "grid_tuning.h"
int main(void)
{
    const double lo[3] = {0.0, 0.0, 0.0}, hi[3] = {1.0, 2.0, 0.0};
    int out[3];
    if (gridcal_compact(1000.0, lo, hi, out) != 0) return 1;
    if (gridcal_general(1e9, 3e9, lo, hi, out) != 0) return 2;
    if (gridcal_nested(GRIDCAL_MIXED, 3, 3, 1.0, lo, hi, 6.0, out) != 0) return 3;
    return out[0] >= 1 && out[1] >= 1 && out[2] >= 1 ? 0 : 4;
}
"""


@needs_gcc
@pytest.mark.parametrize("mode", ["calibration", "ratio"])
def test_header_compiles_as_c99(tmp_path, mode):
    text = header_text(make_calibration()) if mode == "calibration" else header_text(ratio=2.5)
    exe = compile_c(tmp_path, text, SMOKE)
    assert subprocess.run([str(exe)]).returncode == 0


@needs_gxx
def test_header_compiles_as_cxx17(tmp_path):
    exe = compile_c(tmp_path, header_text(make_calibration()), SMOKE, cxx=True)
    assert subprocess.run([str(exe)]).returncode == 0


@needs_gcc
def test_constants_can_be_overridden(tmp_path):
    prog = """
#include <stdio.h>
#include "grid_tuning.h"
int main(void) { const double lo[3] = {0, 0, 0}, hi[3] = {1, 1, 1}; int o[3];
  gridcal_compact(1000.0, lo, hi, o); printf("%.17g %.17g %d %d %d\\n", GRIDCAL_RATIO, GRIDCAL_T_STEP_NS,
  o[0], o[1], o[2]); return 0; }
"""
    (tmp_path / "grid_tuning.h").write_text(header_text(make_calibration()))
    (tmp_path / "o.c").write_text(prog)
    exe = tmp_path / "o"
    subprocess.run([GCC, "-std=c99", *WARNINGS, *FP_FLAGS, "-DGRIDCAL_RATIO=2.0", "-I", str(tmp_path),
                    str(tmp_path / "o.c"), "-o", str(exe), "-lm"], check=True)
    r, t_step, *res = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    assert float(r) == 2.0 and float(t_step) == PLANTED["t_step_ns"]
    assert tuple(int(x) for x in res) == P.paper_resolutions(1000.0, [0] * 3, [1] * 3, 2.0, 1, "compact")[0]


# --- hostile host text --------------------------------------------------------------------------


@pytest.mark.parametrize("cpu", HOSTILE_CPUS)
def test_sanitized_text_cannot_leave_a_comment(cpu):
    s = sanitize_comment(cpu)
    assert all(" " <= c <= "~" for c in s)
    for bad in ("*/", "/*", "\\", "??"):
        assert bad not in s


@needs_gcc
def test_hostile_cpu_names_leave_the_header_harmless(tmp_path):
    fp = {f"extra_{j}": name for j, name in enumerate(HOSTILE_CPUS)}
    cal = make_calibration(cpu=" | ".join(HOSTILE_CPUS), governor=HOSTILE_CPUS[2], os=HOSTILE_CPUS[3], **fp)
    cal["fingerprint"]["kernel_build"] = HOSTILE_CPUS[5]
    text = header_text(cal, source="calib*/ration.json")
    assert text.isascii()
    exe = compile_c(tmp_path, text, SMOKE)  # no #error fired, GRIDCAL_RATIO intact
    assert subprocess.run([str(exe)]).returncode == 0
    cpu_line = next(line for line in text.splitlines() if line.startswith(" *   CPU:"))
    assert "#error x" in cpu_line and "* /" in cpu_line  # neutralised, still readable, in the comment
    assert all(not line.lstrip().startswith("#error x") for line in text.splitlines())
    # the preprocessor sees each host string inside its comment: none of it survives, no #error is active
    pre = subprocess.run([GCC, "-std=c99", "-E", "-P", "-x", "c", "-"], input=text, capture_output=True,
                         text=True, check=True).stdout
    for word in ("injected", "trigraph", "crlf", "#error", "EPYC"):
        assert word not in pre


def test_sanitize_keeps_ordinary_names():
    name = "AMD EPYC 7763 64-Core Processor"
    assert sanitize_comment(name) == name
    assert sanitize_comment(None) == "null" and sanitize_comment(["-O2", "-std=c99"]) == '["-O2","-std=c99"]'
    assert len(sanitize_comment("x" * 1000)) == 160


# --- the command line ------------------------------------------------------------------------------


def test_cli_writes_the_header_from_the_default_calibration(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    write_cal(tmp_path / "calibration.json", make_calibration())
    assert main(["export", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["header"] == "grid_tuning.h" and out["functions"] == list(FUNCTIONS)
    assert set(out["constants"]) == {"t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "ratio"}
    for key, med in PLANTED.items():
        assert out["constants"][key]["median"] == med
        assert out["constants"][key]["ci95"] == [0.8 * med, 1.2 * med]
    text = (tmp_path / "grid_tuning.h").read_text()
    assert "#define GRIDCAL_RATIO 0.9263\n" in text and "#ifndef GRIDCAL_T_INT_NS" in text
    assert "95% interval [16.352, 24.528]" in text  # T_int's interval in its comment
    for word in ("Test CPU @ 3.0GHz", "2026-11-22", "-ffp-contract=off", "instruction set: avx2",
                 "schema version: 1"):
        assert word in text
    for fn in FUNCTIONS:
        assert f" {fn}(" in text


def test_cli_ratio_and_custom_header(tmp_path, capsys):
    dest = tmp_path / "sub.h"
    assert main(["export", "--ratio", "1.5", "--header", str(dest), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["constants"] == {"ratio": {"macro": "GRIDCAL_RATIO", "unit": "dimensionless", "median": 1.5,
                                          "ci95": None}}
    text = dest.read_text()
    assert "#define GRIDCAL_RATIO 1.5\n" in text and "GRIDCAL_T_STEP_NS" not in text


def _fails(argv, capsys, *words):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("calibrate: error: ") and err.count("\n") == 1, err
    for w in words:
        assert w in err, err


def test_cli_without_calibration_says_what_to_do(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _fails(["export"], capsys, "calibrate run", "--ratio")
    assert list(tmp_path.iterdir()) == []


def test_cli_bad_calibrations(tmp_path, capsys):
    dest = tmp_path / "grid_tuning.h"
    _fails(["export", "--calibration", str(tmp_path / "nope.json"), "--header", str(dest)], capsys, "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text('{"schema_version": 1, "fingerprint": ')
    _fails(["export", "--calibration", str(bad), "--header", str(dest)], capsys, "not valid JSON")
    bad.write_bytes(b"\xff\xfe garbage")
    _fails(["export", "--calibration", str(bad), "--header", str(dest)], capsys, "not UTF-8")
    _fails(["export", "--calibration", str(tmp_path), "--header", str(dest)], capsys, "directory")
    _fails(["export", "--ratio", "0", "--header", str(dest)], capsys, "positive")
    _fails(["export", "--ratio", "1", "--calibration", str(bad)], capsys, "not allowed with")
    assert not dest.exists()


def test_cli_bad_destinations_leave_no_file(tmp_path, capsys):
    cal = str(write_cal(tmp_path / "c.json", make_calibration()))
    (tmp_path / "adir").mkdir()
    _fails(["export", "--calibration", cal, "--header", str(tmp_path / "adir")], capsys, "directory")
    _fails(["export", "--calibration", cal, "--header", str(tmp_path / "missing" / "g.h")], capsys, "does not exist")
    (tmp_path / "afile").write_text("x")
    _fails(["export", "--calibration", cal, "--header", str(tmp_path / "afile" / "g.h")], capsys, "not a directory")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "afile", "c.json"]
    assert list((tmp_path / "adir").iterdir()) == []


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="running as root: a read-only directory is still writable")
def test_cli_read_only_directory(tmp_path, capsys):
    cal = str(write_cal(tmp_path / "c.json", make_calibration()))
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        _fails(["export", "--calibration", cal, "--header", str(ro / "g.h")], capsys, "not writable")
        assert list(ro.iterdir()) == []
    finally:
        ro.chmod(0o755)


def test_existing_header_is_kept_on_failure(tmp_path, capsys):
    dest = tmp_path / "grid_tuning.h"
    dest.write_text("old")
    _fails(["export", "--calibration", str(tmp_path / "nope.json"), "--header", str(dest)], capsys)
    assert dest.read_text() == "old"
