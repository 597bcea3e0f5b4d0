"""`--live [HOST:]PORT` and `--live-rate HZ`, the same on every command that can serve a live
view (`run`, `connect`, `swarm`, `vehicle`); the server is cosim/log/live.py."""
from __future__ import annotations

import math

from controller.errors import Se3SyncError

from . import require

__all__ = ["add_live_options", "live_target"]

DEFAULT_RATE = 30.0


def add_live_options(p, insecure: bool = False) -> None:
    """Adds --live and --live-rate (and --insecure, for a command that has none)."""
    p.add_argument("--live", metavar="[HOST:]PORT",
                   help="serve the run live over Foxglove's WebSocket protocol (the log's "
                        "channels: 3D scene, frames, edge errors, θ, V̄, jumps) on this port "
                        "(0: the OS chooses; the URL is printed), on 127.0.0.1 unless HOST is "
                        "given; a non-loopback HOST needs --insecure. Needs the 'live' extra "
                        "(foxglove-sdk). See docs/live.md")
    p.add_argument("--live-rate", type=float, default=DEFAULT_RATE, metavar="HZ",
                   help=f"with --live: frames per second of wall time at most (default "
                        f"{DEFAULT_RATE:g}); jumps are always sent")
    if insecure:
        p.add_argument("--insecure", action="store_true",
                       help="with --live: allow a HOST reachable from other machines (the live "
                            "view has no authentication)")


def live_target(args):
    """None without --live; else (host, port, rate), checked before any work starts."""
    live = getattr(args, "live", None)
    rate = getattr(args, "live_rate", DEFAULT_RATE)
    if not (math.isfinite(rate) and 0 < rate <= 1000):
        raise Se3SyncError(f"--live-rate: must be in (0, 1000] frames per second, got {rate:g}")
    if live is None:
        return None
    from ..log.live import parse_live

    host, port = parse_live(live, bool(getattr(args, "insecure", False)))
    require("foxglove")
    return host, port, float(rate)
