"""Where the telemetry goes: the sinks and their settings, the viewer a run streams to, the .rrd it leaves.

Sinks: ``"rrd"`` file (complete after the telemetry process closes: its child writes it without rerun's
footer, whose per-chunk manifest would grow the child for as long as the run lasts, and the close then
adds the footer in a process of its own: :func:`finish_rrd`); ``"spawn"`` starts ``rerun --bind <bind_ip>
--port <port>`` (never 0.0.0.0 unless configured) and connects; ``"connect"`` connects to ``connect_url``;
``"serve"`` hosts a gRPC server on ``bind_ip``; ``"off"`` starts nothing. The telemetry process itself is
:mod:`rt_ident.processes.telemetry`.
"""

from __future__ import annotations

import ipaddress
import logging
import math
import os
import socket
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from rt_ident.errors import ConfigError

log = logging.getLogger(__name__)

SINKS: tuple[str, ...] = ("rrd", "spawn", "connect", "serve", "off")
DEFAULT_PORT = 9876


def default_sink(env: Mapping[str, str] | None = None) -> str:
    """``"spawn"`` when a display is available, else ``"rrd"``."""
    return "spawn" if has_display(env) else "rrd"


@dataclass(frozen=True)
class TelemetryConfig:
    """Where telemetry goes and how much of it. Validated on construction (no I/O)."""

    sink: str = "rrd"
    rrd_path: str | None = None
    connect_url: str | None = None
    bind_ip: str = "127.0.0.1"
    decimation: int = 1
    application_id: str = "rt_ident"
    port: int = DEFAULT_PORT  # viewer port for "spawn", server port for "serve"
    queue_size: int = 64  # blocks buffered between the loop and the child
    ring_bytes: int = 8 << 20  # and at most this many bytes of them
    flush_timeout: float = 2.0  # child: max wait for rerun to flush at close
    # child: send at most every batch_seconds (one chunk per entity per batch). Rerun stores each
    # send_columns as its own chunk; one per 20-ms block gives ~8000 tiny chunks in 10 s and
    # 2.4 MB/s of .rrd. Half a second keeps the live view fluid and the chunks big enough to compress.
    batch_seconds: float = 1.0
    min_free_bytes: int = 4 << 20  # an .rrd sink stops (and says so) when its filesystem has less left
    finish_timeout: float = 60.0   # close(): max wait for the .rrd's footer (finish_rrd); else left without one

    def __post_init__(self) -> None:
        if self.sink not in SINKS:
            raise ConfigError("sink", f"must be one of {', '.join(SINKS)}, got {self.sink!r}")
        if self.sink == "rrd" and not self.rrd_path:
            raise ConfigError("rrd_path", 'required when sink == "rrd"')
        if self.sink == "connect":
            url = self.connect_url or ""
            if not url.startswith(("rerun://", "rerun+http://", "rerun+https://")) or not url.endswith("/proxy"):
                raise ConfigError("connect_url", f"must look like rerun+http://HOST:PORT/proxy, got {url!r}")
        try:
            ipaddress.ip_address(self.bind_ip)
        except ValueError as e:
            raise ConfigError("bind_ip", f"not an IP address: {self.bind_ip!r}") from e
        if isinstance(self.decimation, bool) or not isinstance(self.decimation, int) or self.decimation < 1:
            raise ConfigError("decimation", f"must be an integer >= 1, got {self.decimation!r}")
        if not isinstance(self.port, int) or not 1 <= self.port <= 65535:
            raise ConfigError("port", f"must be in 1..65535, got {self.port!r}")
        if not isinstance(self.queue_size, int) or self.queue_size < 1:
            raise ConfigError("queue_size", f"must be an integer >= 1, got {self.queue_size!r}")
        if isinstance(self.ring_bytes, bool) or not isinstance(self.ring_bytes, int) or self.ring_bytes < 1 << 16:
            raise ConfigError("ring_bytes", f"must be an integer >= 65536, got {self.ring_bytes!r}")
        if not self.application_id:
            raise ConfigError("application_id", "must not be empty")
        if not (math.isfinite(self.flush_timeout) and self.flush_timeout > 0):
            raise ConfigError("flush_timeout", f"must be > 0 s, got {self.flush_timeout!r}")
        if not (math.isfinite(self.finish_timeout) and self.finish_timeout > 0):
            raise ConfigError("finish_timeout", f"must be > 0 s, got {self.finish_timeout!r}")
        if not (math.isfinite(self.batch_seconds) and 0 <= self.batch_seconds <= 10):
            raise ConfigError("batch_seconds", f"must be in 0..10 s, got {self.batch_seconds!r}")


def viewer_command(cfg: TelemetryConfig) -> list[str]:
    """The command that starts a local viewer bound to ``cfg.bind_ip:cfg.port`` (sink "spawn")."""
    return [sys.executable, "-m", "rerun_cli", "--bind", cfg.bind_ip, "--port", str(cfg.port),
            "--memory-limit", "25%", "--hide-welcome-screen"]


def _local_host(bind_ip: str) -> str:
    return "127.0.0.1" if ipaddress.ip_address(bind_ip).is_unspecified else bind_ip


def serve_port(bind_ip: str, configured: int | None) -> int:
    """The port to serve on: the configured one (refused in one line when taken), else 9876, or a
    free port the system picks when 9876 is taken (a second run beside the first)."""
    def free(port: int) -> bool:
        with socket.socket(socket.AF_INET6 if ":" in bind_ip else socket.AF_INET) as s:
            try:
                s.bind((bind_ip, port))
            except OSError:
                return False
            return True

    if configured is not None:
        if not free(configured):
            raise ConfigError("telemetry.port", f"{bind_ip}:{configured} is in use (another run serving?); "
                                                "choose another port or leave it unset for a free one")
        return configured
    if free(DEFAULT_PORT):
        return DEFAULT_PORT
    with socket.socket(socket.AF_INET6 if ":" in bind_ip else socket.AF_INET) as s:
        s.bind((bind_ip, 0))
        port = int(s.getsockname()[1])
    log.warning("telemetry: port %d is in use; serving on %d instead", DEFAULT_PORT, port)
    return port


def port_open(host: str, port: int) -> bool:
    """Whether something accepts a connection at ``host:port`` within 0.2 s."""
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


#: Sinks that send to a viewer over a gRPC client: rerun buffers and retries without telling the
#: caller, so whether the viewer got the data is checked at the end (the telemetry process's close).
CLIENT_SINKS = ("connect", "spawn")


def viewer_address(cfg: TelemetryConfig) -> tuple[str, int]:
    """(host, port) a client sink sends to: the connect URL's, or the spawned viewer's."""
    if cfg.sink == "connect" and cfg.connect_url:
        from urllib.parse import urlparse

        u = urlparse(cfg.connect_url.replace("rerun+", "", 1).replace("rerun://", "http://", 1))
        try:
            port = u.port
        except ValueError:
            port = None
        return u.hostname or "127.0.0.1", port or DEFAULT_PORT
    return _local_host(cfg.bind_ip), cfg.port


def has_display(env: Mapping[str, str] | None = None) -> bool:
    """A display a viewer window can open on (X11 or Wayland)."""
    env = os.environ if env is None else env
    return bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY") or env.get("WAYLAND_SOCKET"))


def spawn_refusal(cfg: TelemetryConfig, env: Mapping[str, str] | None = None) -> str | None:
    """Why ``--spawn`` cannot show the dashboard here (no display, as in an ssh session, and no viewer
    already listening where it would connect), or None."""
    if cfg.sink != "spawn" or has_display(env) or port_open(*viewer_address(cfg)):
        return None
    return ("no display here for a viewer window (DISPLAY and WAYLAND_DISPLAY unset, as in an ssh session): "
            "leave the dashboard to its .rrd file (the default; open it later with rerun FILE), or --serve and "
            "connect a viewer from a machine with a display")


def ensure_viewer(cfg: TelemetryConfig, wait_s: float = 15.0) -> str:
    """Start a local viewer on ``cfg.bind_ip:cfg.port`` unless one listens there already (it outlives
    the run, in its own session); returns the URL an SDK connects to. Waits up to ``wait_s`` for it."""
    host = _local_host(cfg.bind_ip)
    if not port_open(host, cfg.port):
        env = dict(os.environ, CI=os.environ.get("CI", "1"))
        subprocess.Popen(viewer_command(cfg), env=env, start_new_session=True, stdin=subprocess.DEVNULL,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + wait_s
        while not port_open(host, cfg.port) and time.monotonic() < deadline:
            time.sleep(0.1)
    return f"rerun+http://{host}:{cfg.port}/proxy"


def disk_full(path: str | None, min_free: int) -> str | None:
    """Why an .rrd sink cannot go on writing (its filesystem is full), or None. Rerun's file sink
    writes in a thread of its own and reports a failed write only to its log, never to the caller:
    so the free space is checked before each batch instead."""
    if not path:
        return None
    try:
        st = os.statvfs(Path(path).resolve().parent)
    except OSError:
        return None
    free = st.f_bavail * st.f_frsize
    if free < min_free:
        return f"no space left on the device of {path} ({free} bytes free)"
    return None


def _rerun_cli() -> str | None:
    """The rerun binary itself, not the ``rerun`` script (whose child would outlive a kill at a timeout)."""
    try:
        import rerun_cli
    except ImportError:
        return None
    exe = Path(rerun_cli.__file__).with_name("rerun")
    return str(exe) if exe.is_file() else None


def finish_rrd(path: str, timeout: float, min_free: int = 0) -> str | None:
    """Add rerun's footer (the chunk manifest ``RrdReader.store()`` and ``rerun rrd verify`` need) to
    the footerless .rrd at ``path``. None when done, else why not; the file is then left as it was
    (complete, without a footer), never half rewritten.

    ``rerun rrd filter`` with no filter copies every message as it is and ends the copy with the
    footer; the copy then replaces the file. It runs as a process of its own: the manifest it builds
    is freed when it exits, and it is killed at ``timeout`` (its copy removed)."""
    p = Path(path).resolve()
    tmp = p.with_name(p.name + ".part")
    exe = _rerun_cli()
    if exe is None:
        return "the rerun CLI was not found"
    try:
        size = p.stat().st_size
        st = os.statvfs(p.parent)
    except OSError as e:
        return f"{p}: {e.strerror or e}"
    if st.f_bavail * st.f_frsize < size + min_free:
        return f"no room for a {size / 1e6:.0f} MB copy beside {p}"
    env = dict(os.environ, CI=os.environ.get("CI", "1"), RUST_LOG="warn")   # no analytics config, no INFO lines
    proc = subprocess.Popen([exe, "rrd", "filter", str(p), "-o", str(tmp)], env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    done = False
    try:
        try:
            _, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            return f"not done within {timeout:g} s ({size / 1e6:.0f} MB)"
        if proc.returncode != 0 or not tmp.is_file():
            last = err.decode(errors="replace").strip().splitlines()[-1:] or [f"exit code {proc.returncode}"]
            return f"rerun rrd filter failed: {last[0][-300:]}"
        os.replace(tmp, p)
        done = True
        return None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if not done:
            tmp.unlink(missing_ok=True)
