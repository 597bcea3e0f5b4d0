"""Sub-command `export`: a run log's time series to CSV, Parquet, NumPy .npz or MATLAB .mat."""
from __future__ import annotations

import sys

from controller.errors import Se3SyncError

from ..files import check_output
from . import require

__all__ = ["register"]

FORMATS = (".csv", ".parquet", ".npz", ".mat")
CHANNEL_NAMES = ("edges", "tf", "agents", "lyapunov", "jumps")


def register(sub) -> None:
    p = sub.add_parser(
        "export", help="export a run log's time series to CSV, Parquet, .npz or .mat",
        description="Export the time series of an se3sync MCAP log (JSON or CDR): time; per "
                    "edge θ_k, μ_U, ‖I − R̄_k‖_F, ‖p̄_k‖, U and whether it jumped (edges); per "
                    "agent position and quaternion (tf), ω, v, torque and force (agents); V̄ "
                    "and k_X ΣU (lyapunov); and every jump as an event (jumps: t, edge, θ⁻, θ⁺, "
                    "μ_U; never decimated). The format follows the suffix of -o: .csv and "
                    ".parquet write one row per record and the jumps beside it in "
                    "STEM.jumps.csv / STEM.jumps.parquet; .npz (NumPy) and .mat (MATLAB, "
                    "scipy.io) hold everything in one file. Units: in a '# units:' line of the "
                    "CSV, in Parquet's field metadata, in the 'units' entry of .npz and .mat. "
                    "Values are the log's, unchanged (CSV: shortest round-trip text). Parquet "
                    "needs pyarrow (the 'sweep' extra). Files are written to a temporary name "
                    "and renamed: an error or Ctrl-C leaves none. Exit codes: 0 ok, 2 bad input, "
                    "130/143 interrupted (nothing written).")
    p.add_argument("log", help="an MCAP log written by `se3sync run/connect/swarm --log`")
    p.add_argument("-o", "--output", required=True, metavar="FILE",
                   help="output file: .csv, .parquet, .npz or .mat")
    p.add_argument("--channels", metavar="A,B,...",
                   help=f"comma-separated subset of {','.join(CHANNEL_NAMES)} (default: every "
                        "one the log has)")
    p.add_argument("--tmin", type=float, metavar="S",
                   help="first simulated time exported, s (records and jumps at t >= S)")
    p.add_argument("--tmax", type=float, metavar="S",
                   help="last simulated time exported, s (records and jumps at t <= S)")
    p.add_argument("--every", type=int, default=1, metavar="K",
                   help="decimation: keep every K-th record of the window (default 1: all; the "
                        "log itself holds records at the scenario's simulation.log_rate); jumps "
                        "are all kept")
    p.set_defaults(func=_cmd_export)


def _cmd_export(args) -> int:
    if args.every < 1:
        raise Se3SyncError(f"--every: must be >= 1, got {args.every}")
    out = check_output("--output", args.output, FORMATS)
    if out.suffix.lower() == ".parquet":
        require("pyarrow")   # before the log is read: a missing extra fails at once
    from ..log.export import export_log, jumps_path

    if out.suffix.lower() in (".csv", ".parquet"):
        check_output("--output", jumps_path(out), FORMATS)
    info = export_log(args.log, out, channels=args.channels, tmin=args.tmin, tmax=args.tmax,
                      every=args.every)
    what = f"{info['rows']} records, {info['columns']} columns"
    if info["jumps"] is not None:
        what += f", {info['jumps']} jumps"
    print(f"wrote {', '.join(info['files'])} ({what})", file=sys.stderr)
    return 0
