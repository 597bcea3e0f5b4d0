"""Helpers of the attack tests (issue 29; no tests here): UDP datagrams with a forged source
address, reserved free ports, and scenario files that put a swarm on them."""
from __future__ import annotations

import os
import socket
import struct
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def os_ports(n: int) -> list:
    """n distinct ports, free on 127.0.0.1 (UDP and TCP), for processes that must be told their
    ports before they bind them: a block from `bridge.mavlink.link.free_base_port`, below the
    OS's ephemeral range and reserved by a lock file. (Bound to port 0 and let go, a port could
    be handed to any other socket of the machine before the process bound it: a run under load
    failed so, "Address already in use", on a port of the ephemeral range.)"""
    from bridge.mavlink.link import free_base_port

    base = free_base_port(n)
    return list(range(base, base + n))


def swarm_scenario(tmp_path, n_agents: int = 6, extra: str = "", name: str = "swarm") -> Path:
    """hil_6uav (or its first three agents, a path 1–2–3) with every agent's and every vehicle's
    port given explicitly from `os_ports`, written to tmp_path."""
    text = (ROOT / "scenarios" / "hil_6uav.toml").read_text()
    if n_agents == 3:
        text = _three_agents(text)
    ports = os_ports(2 * n_agents)
    text += "\n[network]\n" + extra
    for i in range(1, n_agents + 1):
        text += f"\n[[network.agent]]\nid = {i}\nport = {ports[n_agents + i - 1]}\n"
    for i in range(1, n_agents + 1):
        text += f"\n[[bridge.vehicle]]\nid = {i}\nendpoint = \"udpin:127.0.0.1:{ports[i - 1]}\"\n"
    p = Path(tmp_path) / f"{name}.toml"
    p.write_text(text)
    return p


def _three_agents(text: str) -> str:
    import tomllib

    d = tomllib.loads(text)
    assert d["graph"]["edges"][:2] == [[1, 2], [2, 3]], d["graph"]
    lines = []
    for ln in text.splitlines():
        if ln.startswith("edges"):
            ln = "edges = [[1, 2], [2, 3]]"
        elif ln.startswith("count = 6"):
            ln = "count = 3"
        lines.append(ln)
    return "\n".join(lines) + "\n"


def _checksum(b: bytes) -> int:
    if len(b) % 2:
        b += b"\0"
    s = sum(struct.unpack(f"!{len(b) // 2}H", b))
    s = (s >> 16) + (s & 0xFFFF)
    s += s >> 16
    return ~s & 0xFFFF


def spoofed_sendto(data: bytes, src: tuple, dst: tuple, raw: socket.socket | None = None) -> None:
    """Sends ``data`` in a UDP datagram from ``src`` (host, port) to ``dst`` built by hand on a
    raw socket (``raw``, or a new one): what an attacker on the network does to look like a
    neighbour (needs root or CAP_NET_RAW; PermissionError otherwise)."""
    s = raw or socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)
    try:
        sip, dip = socket.inet_aton(src[0]), socket.inet_aton(dst[0])
        udp_len = 8 + len(data)
        pseudo = sip + dip + struct.pack("!BBH", 0, socket.IPPROTO_UDP, udp_len)
        udp = struct.pack("!HHHH", src[1], dst[1], udp_len, 0) + data
        csum = _checksum(pseudo + udp) or 0xFFFF
        udp = udp[:6] + struct.pack("!H", csum) + udp[8:]
        ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + udp_len, os.getpid() & 0xFFFF, 0, 64,
                         socket.IPPROTO_UDP, 0, sip, dip)
        s.sendto(ip + udp, (dst[0], 0))
    finally:
        if raw is None:
            s.close()


def can_spoof() -> bool:
    try:
        socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW).close()
        return True
    except PermissionError:
        return False
