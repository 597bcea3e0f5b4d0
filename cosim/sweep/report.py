"""`se3sync sweep-report`: summary and figure of a sweep's results.

Convergence rate per (controller, kind) over the samples that finished (status "ok"; errors
and timeouts are counted apart and reported), with the 95 % Wilson score interval; the time to
converge; the jump counts against Theorem 1's bound ⌈V̄(0)/(k_X δ)⌉; the final errors.
Kinds: "random", "adversarial" (every adversarial sample) and "all".
"""
from __future__ import annotations

import math
from pathlib import Path

from ..files import write_json_atomic
from ..registry import LAWS
from .runner import read_results

__all__ = ["wilson", "summarise", "report", "GROUP_KINDS"]

GROUP_KINDS = ("random", "adversarial", "all")
Z95 = 1.959963984540054


def wilson(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for k successes out of n (NaN, NaN when n = 0)."""
    if n <= 0:
        return float("nan"), float("nan")
    p = k / n
    den = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z / den * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    lo, hi = max(0.0, centre - half), min(1.0, centre + half)
    # rounding: keep p inside the interval (k = 0 or k = n give lo = 0 or hi = 1 exactly)
    return min(lo, p), max(hi, p)


def _in_group(row, kind):
    return kind == "all" or row["kind"] == kind or (kind == "adversarial"
                                                   and row["kind"].startswith("adversarial"))


def summarise(rows) -> dict:
    status = {}
    for r in rows:
        status[r["status"]] = status.get(r["status"], 0) + 1
    seen = list(dict.fromkeys(r["controller"] for r in rows))
    controllers = [c for c in LAWS if c in seen] + [c for c in seen if c not in LAWS]
    groups = []
    for c in controllers:
        for kind in GROUP_KINDS:
            g = [r for r in rows if r["controller"] == c and _in_group(r, kind)]
            if not g:
                continue
            ok = [r for r in g if r["status"] == "ok"]
            conv = [r for r in ok if r["converged"]]
            lo, hi = wilson(len(conv), len(ok))
            tc = sorted(r["t_converge"] for r in conv)
            ratio = [r["n_jumps"] / r["jump_bound"] for r in ok if r["jump_bound"] > 0]
            groups.append({
                "controller": c, "kind": kind, "n": len(g), "n_ok": len(ok),
                "n_error": sum(r["status"] == "error" for r in g),
                "n_timeout": sum(r["status"] == "timeout" for r in g),
                "converged": len(conv),
                "rate": len(conv) / len(ok) if ok else float("nan"),
                "ci_low": lo, "ci_high": hi,
                "t_converge_median": _median(tc), "t_converge_max": tc[-1] if tc else float("nan"),
                "jumps_max": max((r["n_jumps"] for r in ok), default=0),
                "jumps_over_bound": sum(r["n_jumps"] > r["jump_bound"] for r in ok),
                "jump_ratio_max": max(ratio) if ratio else float("nan"),
            })
    return {"n_rows": len(rows), "status": status, "controllers": controllers, "groups": groups,
            "confidence": 0.95}


def _median(xs):
    if not xs:
        return float("nan")
    n = len(xs)
    return xs[n // 2] if n % 2 else 0.5 * (xs[n // 2 - 1] + xs[n // 2])


def _text(path, s) -> str:
    st = ", ".join(f"{k} {v}" for k, v in sorted(s["status"].items()))
    lines = [f"{path}: {s['n_rows']} runs ({st})",
             f"{'controller':10} {'kind':12} {'ok':>5} {'conv':>5} {'rate':>6}  95% Wilson CI    "
             f"t_conv median/max   jumps max (> bound)"]
    for g in s["groups"]:
        extra = ""
        if g["n_error"] or g["n_timeout"]:
            extra = f"  [{g['n_error']} error, {g['n_timeout']} timeout not counted]"
        lines.append(
            f"{g['controller']:10} {g['kind']:12} {g['n_ok']:5d} {g['converged']:5d} "
            f"{g['rate']:6.3f}  [{g['ci_low']:.3f}, {g['ci_high']:.3f}]   "
            f"{g['t_converge_median']:6.3g} / {g['t_converge_max']:<6.3g} s   "
            f"{g['jumps_max']:3d} ({g['jumps_over_bound']}){extra}")
    return "\n".join(lines)


def report(results, output, json_path=None) -> dict:
    """Reads the results, writes the figure (and JSON), returns the summary (with "text")."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt


    rows, meta = read_results(results, option="results")
    s = summarise(rows)
    s["file"] = str(results)
    s["settings"] = meta.get("settings", {})
    s["text"] = _text(results, s)

    palette = ("tab:blue", "tab:red", "tab:green", "tab:purple", "tab:orange", "tab:brown")
    colors = {c: palette[k % len(palette)] for k, c in enumerate(s["controllers"])}
    fig, ax = plt.subplots(2, 2, figsize=(12, 8.5))
    title = meta.get("scenario_name", Path(results).stem)
    fig.suptitle(f"se3sync sweep: {title} ({s['n_rows']} runs)")

    # (a) convergence rate with Wilson intervals
    a = ax[0, 0]
    kinds = [k for k in GROUP_KINDS if any(g["kind"] == k for g in s["groups"])]
    width = 0.8 / max(1, len(s["controllers"]))
    for ci, c in enumerate(s["controllers"]):
        for ki, k in enumerate(kinds):
            g = next((g for g in s["groups"] if g["controller"] == c and g["kind"] == k), None)
            if g is None or g["n_ok"] == 0:
                continue
            x = ki + (ci - (len(s["controllers"]) - 1) / 2) * width
            a.bar(x, g["rate"], width * 0.9, color=colors.get(c), alpha=0.8,
                  label=c if ki == 0 else None)
            a.errorbar(x, g["rate"], yerr=[[max(0.0, g["rate"] - g["ci_low"])],
                                           [max(0.0, g["ci_high"] - g["rate"])]],
                       color="k", capsize=4)
            a.text(x, 0.02, f"{g['converged']}/{g['n_ok']}", ha="center", va="bottom",
                   fontsize=8, rotation=90)
    a.set_xticks(range(len(kinds)), kinds)
    a.set_ylim(0, 1.22)
    a.set_yticks([0, 0.2, 0.4, 0.6, 0.8, 1.0])
    a.set_ylabel("converged fraction (95% Wilson CI)")
    a.set_title("convergence rate")
    a.legend(loc="upper center", ncol=2)

    # (b) time to converge
    b = ax[0, 1]
    tmax = max((r["t_converge"] for r in rows if r["status"] == "ok" and r["converged"]),
               default=1.0)
    bins = max(5, min(40, int(math.sqrt(max(1, len(rows))) * 2)))
    for c in s["controllers"]:
        for k, ls in (("random", "-"), ("adversarial", "--")):
            t = [r["t_converge"] for r in rows if r["controller"] == c and _in_group(r, k)
                 and r["status"] == "ok" and r["converged"]]
            if t:
                b.hist(t, bins=bins, range=(0, tmax * 1.05 + 1e-9), histtype="step",
                       linestyle=ls, color=colors.get(c), label=f"{c}, {k} ({len(t)})")
    b.set_xlabel("time to converge (s)")
    b.set_ylabel("samples")
    b.set_title("time to converge (converged samples)")
    if b.get_legend_handles_labels()[0]:
        b.legend(fontsize=8)

    # (c) jumps against the bound
    c_ = ax[1, 0]
    hy = [r for r in rows if r["controller"] == "hybrid" and r["status"] == "ok"]
    for k, m in (("random", "o"), ("adversarial", "^")):
        pts = [(r["jump_bound"], r["n_jumps"]) for r in hy if _in_group(r, k)]
        if pts:
            c_.scatter([p[0] for p in pts], [p[1] for p in pts], marker=m, s=14, alpha=0.6,
                       label=f"hybrid, {k}")
    if hy:
        hi = max(max(r["jump_bound"] for r in hy), 1)
        c_.plot([0.5, hi], [0.5, hi], "k:", label="n_jumps = bound")
        c_.set_xscale("log")
        c_.set_yscale("symlog", linthresh=1)
        c_.set_ylim(bottom=-0.3)
        c_.legend(fontsize=8)
    c_.set_xlabel("bound ⌈V̄(0)/(k_X δ)⌉")
    c_.set_ylabel("number of jumps")
    c_.set_title("jumps against Theorem 1's bound")

    # (d) final errors
    d = ax[1, 1]
    tol = meta.get("settings", {}).get("rot_tol")
    for c in s["controllers"]:
        for k, m in (("random", "o"), ("adversarial", "^")):
            pts = [(r["sample"], max(r["rot_err"], 1e-16)) for r in rows if r["controller"] == c
                   and _in_group(r, k) and r["status"] == "ok"]
            if pts:
                d.scatter([p[0] for p in pts], [p[1] for p in pts], marker=m, s=12, alpha=0.6,
                          color=colors.get(c), label=f"{c}, {k}")
    if tol:
        d.axhline(tol, color="k", ls=":", label=f"rot_tol {tol:g}")
    d.set_yscale("log")
    d.set_xlabel("sample index (adversarial first)")
    d.set_ylabel("final max_k ‖I − R̄_k‖_F")
    d.set_title("final rotation error")
    if d.get_legend_handles_labels()[0]:
        d.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(output, dpi=110)
    plt.close(fig)
    if json_path is not None:
        write_json_atomic(json_path, s)
    return s
