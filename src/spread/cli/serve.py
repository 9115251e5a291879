"""What the two servers (``spread-dashboard``, ``spread-view``) check before they start, so that they either serve
or exit non-zero in one line (docs/robustness.md, round 4):

* the port is a number in 1–65535 and nothing listens on it yet (:func:`check_port`: before, a busy port printed
  the other server's URL and hung);
* the host is a loopback address unless ``allow_remote=true`` says otherwise (:func:`check_host`): neither server
  has any authentication, so listening on ``0.0.0.0`` or a LAN address lets anyone who reaches the machine read
  (the dashboard: and change) every run or scene it serves; with ``allow_remote=true`` a warning says so.
"""

from __future__ import annotations

import errno
import ipaddress
import socket
import sys

LOOPBACK_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost")


def check_port(command: str, text: str, host: str) -> int:
    """``text`` as a port that ``host`` can listen on now; ``SystemExit`` in one line otherwise."""
    text = str(text).strip()
    if not text.isdigit() or not 1 <= int(text) <= 65535:
        raise SystemExit(f"{command}: port={text}: not a port number (1-65535)")
    port = int(text)
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise SystemExit(f"{command}: host={host}: cannot be resolved ({exc.strerror})") from None
    family, _, _, _, address = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the servers do: TIME_WAIT is no obstacle
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                raise SystemExit(f"{command}: port {port} on {host} is in use (another server listens there); "
                                 f"choose another port=") from None
            if exc.errno in (errno.EACCES, errno.EPERM):
                raise SystemExit(f"{command}: port {port} on {host}: not allowed for this user (ports below 1024 "
                                 f"need privileges); choose another port=") from None
            raise SystemExit(f"{command}: cannot listen on {host}:{port} ({exc.strerror})") from None
    return port


def is_loopback(host: str) -> bool:
    """Whether ``host`` names this machine's loopback interface only (``localhost``, ``127.x``, ``::1``)."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_host(command: str, host: str, allow_remote: str) -> bool:
    """Whether the server may listen on ``host`` (``allow_remote`` as given: true / false); ``SystemExit`` in one
    line for a non-loopback host without ``allow_remote=true``, a warning on stderr with it."""
    allow = str(allow_remote).strip().lower()
    if allow not in ("true", "false"):
        raise SystemExit(f"{command}: allow_remote={allow_remote}: expected true or false")
    if is_loopback(host):
        return True
    if allow != "true":
        raise SystemExit(f"{command}: host={host} is not a loopback address: the server has no authentication, so "
                         f"anyone who reaches this machine could use it; keep host=127.0.0.1 and forward the port "
                         f"(ssh -L), or say allow_remote=true")
    print(f"{command}: WARNING: listening on {host} with allow_remote=true — there is no authentication: anyone who "
          f"can reach this machine on that port can use this server", file=sys.stderr, flush=True)
    return True
