"""The viewer's web server (viser), started before anything heavy is imported, so that a browser loads the
page while the command reads the run (``bcmocap view``'s start-up)."""

from __future__ import annotations

import contextlib
import io
import socket


def port_free(host: str, port: int) -> bool:
    """Whether a server could listen on ``host:port`` now."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def start_server(host: str, port: int):
    """A viser server on exactly ``host:port``; ValueError (one line) if that port is taken or the host
    cannot be bound (viser alone would move to the next free port)."""
    import viser

    if port and not port_free(host, port):
        raise ValueError(f"port {port} on {host} is in use (choose another with --port)")
    quiet = io.StringIO()
    try:
        with contextlib.redirect_stdout(quiet):  # viser prints a banner; the command prints its own line
            server = viser.ViserServer(host=host, port=port, verbose=False)
    except OSError as exc:
        raise ValueError(f"cannot listen on {host}:{port} ({exc.strerror or exc})") from None
    if port and server.get_port() != port:
        server.stop()
        raise ValueError(f"port {port} on {host} is in use (choose another with --port)")
    return server
