"""One sweep on many processes and hosts, through JAX's multi-controller runtime.

Every process runs the same program (``lgvi-jax sweep ... --coordinator HOST:PORT
--num-processes N --process-id I``, or ``--distributed auto`` under Slurm / Open MPI);
:func:`initialize` connects it to the others with :func:`jax.distributed.initialize`, and
:func:`~lgvi_jax.sweep.run_sweep` then divides the sweep's chunks among the processes
(``jax.process_index()``, ``jax.process_count()``): process ``i`` computes the chunks still
to do whose position in that list is ``i`` modulo ``N``, on its own local devices, and
writes them into the shared output folder. The processes agree through the coordinator's
key-value store and barriers (:class:`Group`): process 0 alone writes the manifest (before
any work) and, once every process is done, the summary, the CSV and the plot.

Faults. A process that cannot reach the coordinator stops with a one-line
:class:`DistributedError` (the command line: exit 2) after at most
``initialization_timeout`` seconds. When a process dies, JAX's coordination service notices
the missing heartbeats and ends every other process (a fatal "another task died" message)
within ``heartbeat_timeout`` seconds (the coordinator's death ends them at once); the
finished chunks stay on disk, and the same command with ``--resume``, with any number of
processes or none, completes the sweep.
"""

from __future__ import annotations

import json
import socket
import time
from typing import Any

__all__ = [
    "HEARTBEAT_TIMEOUT_S",
    "INITIALIZATION_TIMEOUT_S",
    "DistributedError",
    "Group",
    "initialize",
]

#: Seconds a process waits for the coordinator before giving up (the issue: under 60 s).
INITIALIZATION_TIMEOUT_S = 40
#: Seconds without a heartbeat after which JAX declares a process dead and ends the others.
HEARTBEAT_TIMEOUT_S = 60
#: Seconds a clean exit waits for the other processes at JAX's shutdown barrier.
SHUTDOWN_TIMEOUT_S = 60


class DistributedError(RuntimeError):
    """The processes of a distributed sweep could not start or agree (one line)."""


def _split_address(address: str) -> tuple[str, int]:
    host, sep, port = address.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise DistributedError(f"--coordinator {address!r}: expected HOST:PORT (e.g. "
                               "node001:12345)")
    return host, int(port)


def _wait_for_port(host: str, port: int, timeout: float) -> bool:
    """Whether a TCP connection to ``host:port`` succeeds within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host, port), timeout=2):
                return True
        except OSError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.25)


def _port_is_free(port: int) -> bool:
    for family, addr in ((socket.AF_INET6, "::"), (socket.AF_INET, "0.0.0.0")):
        try:
            with socket.socket(family, socket.SOCK_STREAM) as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                s.bind((addr, port))
            return True
        except OSError as err:
            if family == socket.AF_INET6 and err.errno in (97, 99):  # no IPv6 here
                continue
            return False
    return False


def initialize(coordinator_address: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, auto: bool = False,
               initialization_timeout: int = INITIALIZATION_TIMEOUT_S,
               heartbeat_timeout: int = HEARTBEAT_TIMEOUT_S,
               shutdown_timeout: int = SHUTDOWN_TIMEOUT_S) -> tuple[int, int]:
    """Join a multi-process run; returns ``(process_id, num_processes)``.

    Give all three of ``coordinator_address`` (``"HOST:PORT"``, served by process 0),
    ``num_processes`` and ``process_id``, or ``auto=True`` to let JAX read them from the
    environment (Slurm, Open MPI, ...). Call it before any JAX computation. Raises
    :class:`DistributedError` (one line) for bad or incomplete arguments, a coordinator
    that cannot be reached within ``initialization_timeout`` seconds, or a coordinator
    port already in use on process 0: unlike :func:`jax.distributed.initialize`, which
    ends the process on a failed connection, this checks the address first.
    """
    import jax

    given = (coordinator_address, num_processes, process_id)
    if auto:
        if any(v is not None for v in given):
            raise DistributedError("--distributed auto reads the coordinator, the number of "
                                   "processes and the process id from the environment: do "
                                   "not also give --coordinator, --num-processes or "
                                   "--process-id")
        from jax._src import clusters

        try:
            coordinator_address, num_processes, process_id, _ = (
                clusters.ClusterEnv.auto_detect_unset_distributed_params(
                    None, None, None, None, None, initialization_timeout))
        except Exception as err:  # (any detection failure: one line)
            raise DistributedError(f"--distributed auto: {str(err).splitlines()[0]}") from None
        if None in (coordinator_address, num_processes, process_id):
            raise DistributedError("--distributed auto: no cluster environment detected "
                                   "(Slurm, Open MPI, ...); give --coordinator HOST:PORT "
                                   "--num-processes N --process-id I instead")
    elif any(v is None for v in given):
        names = ("--coordinator", "--num-processes", "--process-id")
        missing = [n for n, v in zip(names, given, strict=True) if v is None]
        raise DistributedError(f"a distributed sweep needs --coordinator HOST:PORT, "
                               f"--num-processes N and --process-id I together (missing: "
                               f"{', '.join(missing)})")
    if not isinstance(num_processes, int) or num_processes < 1:
        raise DistributedError(f"--num-processes must be an integer >= 1, got "
                               f"{num_processes!r}")
    if not isinstance(process_id, int) or not 0 <= process_id < num_processes:
        raise DistributedError(f"--process-id must be an integer in 0..{num_processes - 1}, "
                               f"got {process_id!r}")
    host, port = _split_address(coordinator_address)
    if process_id == 0:
        if not _port_is_free(port):
            raise DistributedError(f"--coordinator {coordinator_address}: port {port} is "
                                   "already in use on this host (process 0 serves the "
                                   "coordinator there); choose another port")
    elif not _wait_for_port(host, port, initialization_timeout):
        raise DistributedError(f"--coordinator {coordinator_address}: cannot reach the "
                               f"coordinator (process 0) within {initialization_timeout} s; "
                               "start process 0 first, check the address and the port")
    try:
        jax.distributed.initialize(coordinator_address, num_processes, process_id,
                                   initialization_timeout=initialization_timeout,
                                   heartbeat_timeout_seconds=heartbeat_timeout,
                                   shutdown_timeout_seconds=shutdown_timeout)
    except RuntimeError as err:
        raise DistributedError(f"jax.distributed.initialize: {str(err).splitlines()[0]}"
                               ) from None
    return process_id, num_processes


class Group:
    """The processes of one distributed call, through the coordinator's key-value store:
    ``publish``/``read`` JSON values, ``barrier``, a shared counter. Keys live under a
    prefix unique to the call (every process makes the same calls in the same order)."""

    _calls = 0
    #: Seconds a barrier or a read waits while another process may still be computing
    #: (a dead process ends the others through the heartbeats long before).
    LONG_S = 7 * 24 * 3600
    POLL_S = 0.5

    def __init__(self, name: str):
        import jax
        from jax._src.distributed import global_state

        Group._calls += 1
        self.client = global_state.client
        self.index = jax.process_index()
        self.count = jax.process_count()
        self.prefix = f"lgvi_jax/{name}/{Group._calls}"
        if self.client is None and self.count > 1:
            raise DistributedError("jax.process_count() > 1 but jax.distributed is not "
                                   "initialised through its client")

    def _key(self, key: str) -> str:
        return f"{self.prefix}/{key}"

    def publish(self, key: str, value: Any) -> None:
        self.client.key_value_set(self._key(key), json.dumps(value))

    def read(self, key: str, timeout_s: float | None = None) -> Any:
        ms = int(1000 * (self.LONG_S if timeout_s is None else timeout_s))
        return json.loads(self.client.blocking_key_value_get(self._key(key), ms))

    def try_read(self, key: str) -> Any | None:
        try:
            return json.loads(self.client.key_value_try_get(self._key(key)))
        except Exception:  # (not found)
            return None

    def add(self, key: str, n: int) -> int:
        return int(self.client.key_value_increment(self._key(key), n))

    def barrier(self, name: str, timeout_s: float | None = None) -> None:
        ms = int(1000 * (self.LONG_S if timeout_s is None else timeout_s))
        self.client.wait_at_barrier(self._key(name), ms)

    def wait_for_total(self, key: str, total: int, on_progress=None,
                       failed_key: str | None = None) -> None:
        """Poll the counter ``key`` until it reaches ``total``; raise
        :class:`DistributedError` with the message published under ``failed_key``."""
        last = None
        while True:
            done = self.add(key, 0)
            if on_progress is not None and done != last:
                on_progress(done)
                last = done
            if done >= total:
                return
            if failed_key is not None:
                msg = self.try_read(failed_key)
                if msg is not None:
                    raise DistributedError(msg)
            time.sleep(self.POLL_S)
