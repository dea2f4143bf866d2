"""Benchmark: the recommended uniform grid with and without mailboxing, side by side.

    python tests/benchmarks/mailbox_speedup.py [MESH|SCENE ...] [--repeats K]

Each scene gets the analytic plan's uniform grid twice: as planned without a
mailbox, and as planned with one (the plan then recommends a coarser grid).
Both trace the same isotropic and camera rays (16,384 per batch) in interleaved
rounds on one pinned core, timed by the thread's CPU clock; printed is the
median over rounds of the no-mailbox time over the mailbox time (above 1: the
mailbox is faster).  Not a test: the figures are read off (docs/bench.md).
"""

from __future__ import annotations

import argparse

import numpy as np

from calibrate import Scene
from calibrate.bench import interleaved, make_rays
from calibrate.predict import recommended_grid
from calibrate.protocol import pin_to_one_core

DEFAULT_SCENES = ("sphere", "cylinder196", "cylinder1996", "cylinder19996", "room")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="*", default=list(DEFAULT_SCENES))
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--ratio", type=float, default=1.0, help="T_int/T_step of the plans (default 1)")
    args = ap.parse_args()
    with pin_to_one_core() as pin:
        for name in args.scenes:
            scene = Scene.load(name)
            plain, _ = recommended_grid(scene, ratio=args.ratio, levels="1")
            boxed, _ = recommended_grid(scene, ratio=args.ratio, levels="1", mailbox=True)
            out = []
            for kind in ("isotropic", "camera"):
                o, d = make_rays(scene, kind, 16_384)
                t = interleaved({"plain": lambda run=plain.timed_batch(o, d): run(1),
                                 "mailbox": lambda run=boxed.timed_batch(o, d): run(1)}, args.repeats)
                out.append(f"{kind} {np.median(np.array(t['plain']) / np.array(t['mailbox'])):.2f}")
            print(f"{scene.name}: {plain.resolution} -> {boxed.resolution} with a mailbox; speed-up "
                  + ", ".join(out), flush=True)
        print(pin.note)


if __name__ == "__main__":
    main()
