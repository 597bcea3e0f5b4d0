"""Benchmark of the plant FMU.  Run: python benchmarks/bench_plant.py [--quick] [--against REV]

Prints a table:
  * C cost per body per internal step (1000-body fleet, one big communication step), with
    bodies stepped two at a time (the default) and one at a time (-DSE3SYNC_NO_PAIRS) in the
    same run;
  * cost per communication step (h = 1e-4 = one internal step) of a 6-body FMU:
    fmpy's high-level API (setReal(36) + doStep + getReal(108)) versus the FleetFMU fast path;
  * a 1000-body fleet per communication step (fast path);
  * the optional plant terms: the same per-body cost with the ground and drag on (the bodies fly
    high above the plane), and, with ``--against REV``, the plant compiled from REV's C sources in
    the same run (the terms off must cost what REV costs).
Times are the best of several repeats (wall clock, perf_counter); the cases of one comparison are
timed alternately, so that load on a shared machine hits them alike.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

import _markdown
from plant_fmu import build, layout
from plant_fmu.fast import FleetFMU


def best_of(fn, number, repeat=5):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn(number)
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def fleet(n, fmu_path=None, **terms):
    rng = np.random.default_rng(0)
    f = FleetFMU(n, fmu_path=fmu_path)
    J = np.array([np.diag(rng.uniform(1.0, 1.4, 3)) + 0.05 * (np.ones((3, 3)) - np.eye(3)) for _ in range(n)])
    p0 = np.zeros((n, 3))
    p0[:, 2] = 1e4        # far above a ground at 0 (gravity along -z): the bodies fly
    f.set_parameters(J=J, xi0=rng.normal(size=(n, 6)), p0=p0, gravity=[0.0, 0.0, -9.81], **terms)
    f.initialize()
    return f


def _fmu_from(tree: Path, n: int, out: Path) -> Path:
    """The plant FMU compiled from the C sources of another tree (this tree's build.py)."""
    old = build.C_DIR
    build.C_DIR = tree / "plant_fmu" / "c"
    try:
        return build.build_fmu(n, out)
    finally:
        build.C_DIR = old


def compare_terms(against: str | None, steps: int) -> list:
    """Per body per internal step: terms off, ground + drag on, and (optionally) REV's plant."""
    from _revisions import trees

    n = 1000
    rows = []
    with trees(against) as tr, tempfile.TemporaryDirectory() as tmp:
        cases = {"terms off (this tree)": fleet(n),
                 "ground + drag on (this tree)": fleet(n, ground=True, ground_height=0.0, drag_linear=0.1,
                                                      drag_angular=0.01)}
        if against:
            cases[f"plant of {against}"] = fleet(n, _fmu_from(tr[against], n, Path(tmp) / "old.fmu"))
        best = dict.fromkeys(cases, float("inf"))
        for _ in range(5):
            for name, f in cases.items():
                t0 = time.perf_counter()
                f.do_step(0.0, steps * 1e-4)
                best[name] = min(best[name], (time.perf_counter() - t0) / (n * steps))
        for name, f in cases.items():
            rows.append((f"C integrator, per body per internal step (1000 bodies), {name}", best[name]))
            f.close()
        if against:
            print(f"terms off / {against}: {best['terms off (this tree)'] / best[f'plant of {against}']:.3f}")
        print(f"ground + drag on / off: {best['ground + drag on (this tree)'] / best['terms off (this tree)']:.2f}")
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="fewer iterations")
    ap.add_argument("--against", metavar="REV", help="also time the plant compiled from REV's C sources")
    ap.add_argument("--terms-only", action="store_true", help="only the optional-terms comparison")
    _markdown.add_option(ap)
    args = ap.parse_args(argv)
    with _markdown.Report(args.markdown) as rep:
        bench(args, rep)


def bench(args, rep):
    k = 0.2 if args.quick else 1.0
    rows = compare_terms(args.against, int(1000 * k))
    if args.terms_only:
        _print(rows, rep)
        return

    # 1. C cost per body per internal step
    n_big = 1000
    steps = int(1000 * k)
    with tempfile.TemporaryDirectory() as tmp:
        flags = build.CFLAGS
        build.CFLAGS = flags + ("-DSE3SYNC_NO_PAIRS",)
        try:
            single = build.build_fmu(n_big, Path(tmp) / "single.fmu")
        finally:
            build.CFLAGS = flags
        per = {}
        for name, path in (("two bodies at a time", None), ("one body at a time", single)):
            f = fleet(n_big, path)
            t = best_of(lambda m: [f.do_step(0.0, steps * 1e-4) for _ in range(m)], 1, repeat=3)
            per[name] = t / (n_big * steps)
            rows.append((f"C integrator, per body per internal step (1000 bodies, g != 0), {name}",
                         per[name]))
            f.close()
    print(f"bodies two at a time: {per['one body at a time'] / per['two bodies at a time']:.2f}x "
          f"faster than one at a time")

    # 2. 6 bodies, one internal step per communication step
    n = 6
    f = fleet(n)
    u = np.zeros((n, 6))
    s = f._slave
    vr_in, vr_st, uu = [int(v) for v in layout.vr_input(n)], [int(v) for v in layout.vr_state(n)], [0.0] * 36
    number = int(20000 * k)

    def high_level(m):
        for _ in range(m):
            s.setReal(vr_in, uu)
            s.doStep(0.0, 1e-4)
            s.getReal(vr_st)

    def fast(m):
        set_input, do_step, get_state = f.set_input, f.do_step, f.get_state
        for _ in range(m):
            set_input(u)
            do_step(0.0, 1e-4)
            get_state()

    def fast_buffer(m):
        set_input, do_step, get_state = f.set_input, f.do_step, f.get_state
        f.u[:] = u
        for _ in range(m):
            set_input()  # the wrench was written into f.u
            do_step(0.0, 1e-4)
            get_state()

    def step_only(m):
        do_step = f.do_step
        for _ in range(m):
            do_step(0.0, 1e-4)

    rows.append(("6 bodies, fmpy high-level setReal(36)+doStep+getReal(108)", best_of(high_level, number // 4)))
    rows.append(("6 bodies, FleetFMU fast path set_input+do_step+get_state", best_of(fast, number)))
    rows.append(("6 bodies, fast path writing into FleetFMU.u (no copy)", best_of(fast_buffer, number)))
    rows.append(("6 bodies, FleetFMU do_step alone", best_of(step_only, number)))
    f.close()

    # 3. 1000 bodies per communication step
    f = fleet(n_big)
    u = np.zeros((n_big, 6))

    def fast_big(m):
        for _ in range(m):
            f.set_input(u)
            f.do_step(0.0, 1e-4)
            f.get_state()

    rows.append(("1000 bodies, fast path per communication step (1 internal step)", best_of(fast_big, int(500 * k))))
    f.close()

    _print(rows, rep, per)


def _print(rows, rep, per=None) -> None:
    print(f"plant FMU benchmark ({build.platform_tag()}, FMU compiled with {' '.join(build.CFLAGS)})")
    print(f"{'case':<80} {'time':>12}")
    for name, sec in rows:
        print(f"{name:<80} {sec * 1e6:>9.3f} us")
    rep.table(["case", "time (µs)"], [(name, f"{sec * 1e6:.3f}") for name, sec in rows])
    if per is not None:
        rep.note(f"Bodies two at a time: {per['one body at a time'] / per['two bodies at a time']:.2f}× "
                 f"faster than one at a time. FMU compiled with `{' '.join(build.CFLAGS)}` "
                 f"({build.platform_tag()}); times are the best of several repeats.")


if __name__ == "__main__":
    main()
