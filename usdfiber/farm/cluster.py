"""Dask ``distributed`` clusters for farm bakes and frame sequences.

``--scheduler`` takes a scheduler address (``tcp://host:8786``, ``host:8786``) or
``local:N``, which starts a ``distributed.LocalCluster`` of N worker processes on this
machine (bound to 127.0.0.1). On a farm the scheduler and workers come from dask-jobqueue
(SLURM, PBS, LSF), dask-kubernetes, or ``dask scheduler`` / ``dask worker`` started by
hand; see the README.

Before any work is sent, every worker is checked (:func:`check_workers`): it must run the
same usdfiber and baker version as the client, and it must see the client's cache
directory. The client writes a uniquely named probe file with a random token into the cache;
a worker that cannot read it back is on another filesystem, and the run stops with an
error naming the worker, rather than baking into a cache nobody else reads. Every task
checks the probe again (:func:`verify_probe`), which covers workers that join later.

A worker runs one usdfiber task at a time (:data:`TASK_LOCK`): Dr.Jit already spreads one
trace or render over all the cores it is given, and two in one process would compete for
them. For ``local:N`` each worker gets ``cores / N`` Dr.Jit threads.
"""
from __future__ import annotations

import os
import secrets
import threading
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["FarmError", "LocalFarm", "PROBE_LIFETIME_S", "Probe", "TASK_LOCK", "check_workers", "connect",
           "parse_scheduler", "verify_probe", "write_probe"]

#: Serialises usdfiber tasks within one worker process (see the module docstring).
TASK_LOCK = threading.Lock()


class FarmError(RuntimeError):
    """A farm run that cannot go on (unreachable scheduler, unshared cache, ...); one line."""


@dataclass(frozen=True)
class Probe:
    """A file in the cache holding a random token: whoever reads the token sees the cache."""

    path: str
    token: str


#: Probes stay for this long after a bake (seconds). A task that two clients share runs with
#: one client's probe; if that client finished first and deleted it, a retry of the task would
#: fail its check. So no client deletes its own probe: each new probe removes the stale ones.
PROBE_LIFETIME_S = 86400.0


def write_probe(cache_root: str | os.PathLike[str]) -> Probe:
    """Write a uniquely named probe file under ``cache_root/farm/`` (atomically), removing
    probes older than :data:`PROBE_LIFETIME_S`."""
    import time

    from usdfiber.atomic_file import write_atomic

    d = Path(cache_root) / "farm"
    d.mkdir(parents=True, exist_ok=True)
    now = time.time()
    for old in d.glob("probe-*"):
        try:
            if now - old.stat().st_mtime > PROBE_LIFETIME_S:
                old.unlink()
        except OSError:
            pass  # removed by another client meanwhile
    token = secrets.token_hex(16)
    path = d / f"probe-{uuid.uuid4().hex}"
    write_atomic(path, lambda tmp: Path(tmp).write_text(token))
    return Probe(str(path), token)


def verify_probe(probe: Probe | None, cache_root: str | os.PathLike[str]) -> None:
    """Raise FarmError unless this process reads the probe's token (it sees the client's cache)."""
    if probe is None:
        return
    try:
        seen = Path(probe.path).read_text()
    except OSError as exc:
        seen = f"<{exc.strerror or exc}>"
    if seen != probe.token:
        raise FarmError(f"this worker does not see the cache directory {cache_root} (probe file {probe.path}: "
                        f"{'not found' if seen.startswith('<') else 'other content'}); the cache must be on a "
                        f"filesystem that the client and every worker share")


def _worker_facts(probe: Probe, cache_root: str) -> dict[str, Any]:
    """Run on each worker by :func:`check_workers`."""
    import usdfiber
    from usdfiber.bake.settings import BAKER_VERSION

    facts: dict[str, Any] = {"version": usdfiber.__version__, "baker_version": BAKER_VERSION,
                             "host": os.uname().nodename, "pid": os.getpid(), "error": None}
    try:
        verify_probe(probe, cache_root)
    except FarmError as exc:
        facts["error"] = str(exc)
    return facts


def check_workers(client: Any, cache_root: str | os.PathLike[str], probe: Probe, *,
                  wait_s: float = 60.0) -> list[str]:
    """The workers' addresses after checking each (version, cache visibility); FarmError otherwise.

    Waits up to ``wait_s`` for at least one worker (a jobqueue cluster's workers may still
    be queued).
    """
    import usdfiber
    from usdfiber.bake.settings import BAKER_VERSION

    try:
        client.wait_for_workers(1, timeout=wait_s)
    except TimeoutError:
        raise FarmError(f"the Dask scheduler {client.scheduler.address} has no workers "
                        f"(waited {wait_s:.0f} s)") from None
    facts = client.run(_worker_facts, probe, str(cache_root))
    bad = []
    for addr, f in sorted(facts.items()):
        if f["error"]:
            bad.append(f"worker {addr} ({f['host']}): {f['error']}")
        elif f["version"] != usdfiber.__version__ or f["baker_version"] != BAKER_VERSION:
            bad.append(f"worker {addr} ({f['host']}) runs usdfiber {f['version']} (baker {f['baker_version']}), "
                       f"this client {usdfiber.__version__} (baker {BAKER_VERSION}); install the same "
                       f"version everywhere")
    if bad:
        raise FarmError(bad[0] + (f" (and {len(bad) - 1} more workers)" if len(bad) > 1 else ""))
    return sorted(facts)


class LocalFarm:
    """A client connected to ``--scheduler``; a context manager that closes what it started."""

    def __init__(self, spec: str, *, timeout: float | None = None) -> None:
        self.spec = str(spec).strip()
        self.cluster: Any = None
        self.client: Any = None
        self.timeout = timeout

    def __enter__(self) -> "LocalFarm":
        self.client = connect(self.spec, timeout=self.timeout, farm=self)
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def address(self) -> str:
        return str(self.client.scheduler.address) if self.client is not None else self.spec

    def close(self) -> None:
        import contextlib

        for thing in (self.client, self.cluster):
            if thing is not None:
                with contextlib.suppress(Exception):
                    thing.close()
        self.client = self.cluster = None


def parse_scheduler(spec: str) -> tuple[int, str]:
    """``(N, "")`` for ``local:N`` (``local``: one worker per core), else ``(0, address)`` with
    the address's protocol made explicit (``host:port`` is ``tcp://host:port``); FarmError, one
    line, for a spec that names no scheduler (checked without connecting, so that
    ``bake --dry-run`` refuses what a bake would)."""
    spec = str(spec).strip()
    if spec.startswith("local:") or spec == "local":
        n_text = spec.partition(":")[2] or str(os.cpu_count() or 1)
        try:
            n = int(n_text)
        except ValueError:
            n = 0
        if not 1 <= n <= 256:
            raise FarmError(f"bad --scheduler {spec!r}: local:N needs 1 <= N <= 256 worker processes")
        return n, ""
    expected = "expected an address such as tcp://host:8786, or local:N"
    if not spec or any(c.isspace() for c in spec):
        raise FarmError(f"bad --scheduler {spec!r}: {expected}")
    address = spec if "://" in spec else f"tcp://{spec}"
    scheme, _, where = address.partition("://")
    if scheme in ("tcp", "tls", "ws", "wss"):
        host, port = where, "8786"
        if where.startswith("["):       # [ipv6]:port
            host, _, rest = where[1:].partition("]")
            port = rest[1:] if rest.startswith(":") else ("" if rest else port)
        elif ":" in where:
            host, _, port = where.rpartition(":")
            if ":" in host:
                raise FarmError(f"bad --scheduler {spec!r}: an IPv6 address needs brackets, as in "
                                f"tcp://[::1]:8786; {expected}")
        if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise FarmError(f"bad --scheduler {spec!r}: {expected} (a host and a port in 1..65535)")
    elif scheme not in ("inproc", "ucx"):
        raise FarmError(f"bad --scheduler {spec!r}: unknown protocol {scheme!r}; {expected}")
    return 0, address


def connect(spec: str, *, timeout: float | None = None, farm: LocalFarm | None = None) -> Any:
    """A ``distributed.Client`` for ``spec`` (an address, or ``local:N``); FarmError when unreachable.

    ``timeout``: seconds to wait for the scheduler (default: Dask's
    ``distributed.comm.timeouts.connect``).
    """
    import logging

    try:
        from distributed import Client, LocalCluster

        from usdfiber.farm.worker_plugin import DrjitThreads
    except ImportError as exc:  # pragma: no cover - a dependency
        raise FarmError(f"--scheduler needs the 'distributed' package ({exc}); pip install distributed") from None
    n, address = parse_scheduler(spec)
    if n:
        threads = max(1, (os.cpu_count() or 1) // n)
        try:
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                                   dashboard_address=None, silence_logs=logging.ERROR)
            client = Client(cluster)
            client.register_plugin(DrjitThreads(threads))
        except Exception as exc:  # noqa: BLE001 - one line, whatever went wrong
            raise FarmError(f"cannot start a local Dask cluster of {n} workers: {exc}") from None
        if farm is not None:
            farm.cluster = cluster
        return client
    try:
        import dask

        t = timeout if timeout is not None else dask.config.get("distributed.comm.timeouts.connect")
        return Client(address, timeout=t)
    except (OSError, TimeoutError, ValueError) as exc:
        why = " ".join(str(exc).split()) or type(exc).__name__
        raise FarmError(f"cannot reach the Dask scheduler at {address}: {why}") from None
