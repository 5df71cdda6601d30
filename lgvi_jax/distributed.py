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
``initialization_timeout`` seconds. When a process dies or hangs, a :class:`Watchdog` in
every other process notices its missing heartbeats (keys in the coordinator's key-value
store, one a second) and, ``heartbeat_timeout`` seconds after the last one, ends its own
process with one line on stderr and exit status :data:`EXIT_PROCESS_LOST` (3), before JAX's
coordination service would (it is given a longer timeout, :func:`jax_heartbeat_timeout`,
and would end the process with SIGABRT and a C++ stack trace). The death of process 0,
which serves the coordinator, is reported the same way (``lost the connection to the
coordinator``) thanks to a keeper process holding its connections open (see
:class:`Watchdog`). The finished chunks stay on disk, and the same command with
``--resume``, with any number of processes or none, completes the sweep.
"""

from __future__ import annotations

import atexit
import json
import os
import socket
import stat
import subprocess
import sys
import threading
import time
from typing import Any

__all__ = [
    "EXIT_PROCESS_LOST",
    "HEARTBEAT_TIMEOUT_S",
    "INITIALIZATION_TIMEOUT_S",
    "DistributedError",
    "Group",
    "Watchdog",
    "end_process",
    "initialize",
    "jax_heartbeat_timeout",
    "stop_watchdog",
]

#: Seconds a process waits for the coordinator before giving up (the issue: under 60 s).
INITIALIZATION_TIMEOUT_S = 40
#: Seconds without a heartbeat after which the :class:`Watchdog` declares a process dead
#: and ends the others (the command line's ``--heartbeat-timeout``).
HEARTBEAT_TIMEOUT_S = 60
#: Seconds a clean exit waits for the other processes at JAX's shutdown barrier.
SHUTDOWN_TIMEOUT_S = 60
#: Exit status of a process that the :class:`Watchdog` ends because another process of the
#: sweep stopped (died, hung, lost its connection) or it lost the coordinator.
EXIT_PROCESS_LOST = 3


def jax_heartbeat_timeout(heartbeat_timeout: float) -> int:
    """The heartbeat timeout given to JAX's coordination service for our
    ``heartbeat_timeout``: long enough that the :class:`Watchdog` always ends a process
    first. JAX's clients send a heartbeat every half timeout, so the service may declare a
    process dead as early as half its timeout after the death (``docs/distributed.md``);
    half of ``2 t + 20`` is ``t + 10``, against at most ``t + 2`` for the watchdog."""
    return int(2 * heartbeat_timeout + 20)


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
               heartbeat_timeout: float = HEARTBEAT_TIMEOUT_S,
               shutdown_timeout: int = SHUTDOWN_TIMEOUT_S,
               watchdog: bool = True, prog: str = "lgvi-jax sweep") -> tuple[int, int]:
    """Join a multi-process run; returns ``(process_id, num_processes)``.

    Give all three of ``coordinator_address`` (``"HOST:PORT"``, served by process 0),
    ``num_processes`` and ``process_id``, or ``auto=True`` to let JAX read them from the
    environment (Slurm, Open MPI, ...). Call it before any JAX computation. Raises
    :class:`DistributedError` (one line) for bad or incomplete arguments, a coordinator
    that cannot be reached within ``initialization_timeout`` seconds, or a coordinator
    port already in use on process 0: unlike :func:`jax.distributed.initialize`, which
    ends the process on a failed connection, this checks the address first.

    With ``watchdog`` (and more than one process), a :class:`Watchdog` then runs until
    :func:`~lgvi_jax.sweep.run_sweep` returns (or :func:`stop_watchdog`): a process
    silent for ``heartbeat_timeout`` seconds ends the others with one line
    (``"{prog}: process 1 stopped responding ..."``) and exit status
    :data:`EXIT_PROCESS_LOST`. JAX's own heartbeat timeout is set to
    :func:`jax_heartbeat_timeout` of it. Pass ``watchdog=False`` to use the processes for
    anything else than one sweep (then JAX's timeout is ``heartbeat_timeout`` itself).
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
    watch = watchdog and num_processes > 1
    try:
        jax.distributed.initialize(
            coordinator_address, num_processes, process_id,
            initialization_timeout=initialization_timeout,
            heartbeat_timeout_seconds=(jax_heartbeat_timeout(heartbeat_timeout) if watch
                                       else int(heartbeat_timeout)),
            shutdown_timeout_seconds=shutdown_timeout)
    except RuntimeError as err:
        raise DistributedError(f"jax.distributed.initialize: {str(err).splitlines()[0]}"
                               ) from None
    if watch:
        from jax._src.distributed import global_state

        # A process that left early skipped JAX's shutdown, so JAX declares it dead
        # heartbeat_timeout + 10 s later at the earliest: the grace ends before.
        grace = min(shutdown_timeout / 2, heartbeat_timeout)
        _start_watchdog(Watchdog(global_state.client, process_id, num_processes,
                                 heartbeat_timeout, grace_s=grace, prog=prog))
    return process_id, num_processes


_WATCHDOG: Watchdog | None = None


def _start_watchdog(watchdog: Watchdog) -> None:
    global _WATCHDOG
    if _WATCHDOG is not None:
        _WATCHDOG.stop("done")
    _WATCHDOG = watchdog
    watchdog.start()


def stop_watchdog(state: str = "done") -> None:
    """Tell the other processes, through this process's :class:`Watchdog` (if one runs),
    that this process is ``"done"`` (its part of the sweep is complete: the watchdog
    stops) or has ``"left"`` early (an error, an interrupt: see :meth:`Watchdog.leave`).
    :func:`~lgvi_jax.sweep.run_sweep` calls it when it returns or raises."""
    global _WATCHDOG
    if _WATCHDOG is not None:
        _WATCHDOG.stop(state)
        if state == "done":
            _WATCHDOG = None


def end_process(code: int) -> None:
    """End a process of a distributed sweep that did not complete (its watchdog still
    runs, or has ``"left"``): :meth:`Watchdog.leave` with exit status ``code``. Returns
    at once in any other process (no watchdog, or the sweep completed): then the usual
    exit, through JAX's shutdown barrier, follows. The command line calls it last."""
    if _WATCHDOG is not None:
        _WATCHDOG.leave(code)


_RERUN = "rerun the same command with --resume to finish the sweep"


class Watchdog:
    """Ends this process with one line when another process of the run stops answering.

    Two daemon threads. One publishes this process's heartbeat (``"alive N"``, N counting
    up) under :attr:`PREFIX` in the coordinator's key-value store every ``poll_s`` seconds
    (default ``min(1, timeout_s / 5)``) and reads all processes' keys in one request; the
    other judges from what was read, without touching the network, so that a request that
    hangs (a coordinator that stopped answering) is judged too. Verdicts, each ending the
    process with ``"{prog}: {message}"`` on stderr and :func:`os._exit` (``exit_code``):

    * a process whose heartbeat has not changed for ``timeout_s`` seconds (or never
      appeared): ``process J stopped responding (no heartbeat for T s); rerun ...``;
    * a process that ended this way itself (key ``"stopped MESSAGE"``): its message;
    * a process that ended early (key ``"left"``: an error or an interrupt) while this one
      still runs ``grace_s`` seconds later (the sweep's own error path normally ends this
      one first, with that process's error, at the end of its chunk):
      ``process J ended before the sweep was complete; rerun ...``;
    * no successful exchange with the key-value store for ``timeout_s`` seconds, or three
      failed ones in a row: ``lost the connection to the coordinator (process 0) ...``.

    A process whose key says ``"done"`` (:meth:`stop`) is not watched. Before ending,
    the process publishes ``"stopped MESSAGE"``; process 0, which serves the key-value
    store, then waits (at most ``min(10, timeout_s)`` seconds) until the others have ended
    too, so that they end with this line rather than with JAX's fatal error about the
    coordinator. Files already written are untouched: the sweep writes every file
    atomically, so ``--resume`` completes it.

    **Leaving early** (:meth:`stop` ``("left")``, then :meth:`leave`): a process that ends
    before the sweep is complete skips JAX's shutdown barrier, which would wait for the
    others and then end the process with JAX's fatal error once they are gone; process 0
    first serves the store until the others have ended (at most ``grace_s + 5`` s).

    **Process 0's death.** A JAX client whose connection to the coordinator is closed
    ends its process at once (SIGABRT, a C++ stack trace), before any Python code can
    act; a coordinator that merely stops answering leaves it alone (measured: for 32 s
    and more), so the watchdog's verdict comes first. Process 0 therefore starts a
    *keeper* (:func:`_start_keeper`), a small process that holds copies of its connected
    sockets and exits ``timeout_s + 10`` seconds after process 0 has ended: if process 0
    dies, its connections stay open but silent, and the others end with ``lost the
    connection to the coordinator``. Process 0 stops the keeper before any ordinary exit.
    """

    PREFIX = "lgvi_jax/watchdog/"

    def __init__(self, client: Any, index: int, count: int, timeout_s: float, *,
                 grace_s: float = SHUTDOWN_TIMEOUT_S / 2, prog: str = "lgvi-jax sweep",
                 exit_code: int = EXIT_PROCESS_LOST, poll_s: float | None = None,
                 exit=os._exit):
        self.client, self.index, self.count = client, index, count
        self.timeout_s, self.grace_s = float(timeout_s), float(grace_s)
        self.poll_s = min(1.0, self.timeout_s / 5) if poll_s is None else float(poll_s)
        self.prog, self.exit_code, self._exit = prog, exit_code, exit
        self._lock = threading.Lock()  # guards what the threads share
        self._publish_lock = threading.Lock()  # orders this process's own key's updates
        self._stopped = threading.Event()  # both threads end
        self._published = threading.Event()  # "stopped MESSAGE" is in the store
        self._state = "alive"  # then "done" or "left" (stop), or "stopped" (a verdict)
        self._seen: dict[int, tuple[str | None, float]] = {}  # value, when it last changed
        self._last_ok = 0.0  # when the last exchange with the store succeeded
        self._errors = 0  # failed exchanges in a row
        self._error = ""
        self._ending: str | None = None
        self._beats = 0
        self._keeper: subprocess.Popen | None = None

    def start(self) -> None:
        now = time.monotonic()
        with self._lock:
            self._last_ok = now
            self._seen = {j: (None, now) for j in range(self.count) if j != self.index}
        if self.index == 0:
            self._keeper = _start_keeper(self.timeout_s + 10)
        for target, name in ((self._talk, "talk"), (self._judge, "judge")):
            threading.Thread(target=target, name=f"lgvi-jax-watchdog-{name}",
                             daemon=True).start()
        atexit.register(self._at_exit)  # runs before JAX's own shutdown at exit

    def stop(self, state: str = "done") -> None:
        """Stop judging and leave ``state`` in the store: ``"done"`` (the threads and the
        keeper stop) or ``"left"`` (the store is still read, for :meth:`leave`)."""
        with self._lock:
            if self._state != "alive":
                return
            self._state = state
        try:
            with self._publish_lock:
                self._set(state)
        except Exception:  # (the coordinator is gone: nobody is left to tell)
            pass
        if state == "done":
            self._stopped.set()
            self._stop_keeper()

    def _at_exit(self) -> None:
        """The interpreter's exit (library use; the command line ends by :meth:`leave`):
        the others are told, and JAX's shutdown finds the connections as they were."""
        self.stop("left")
        self._stopped.set()
        self._stop_keeper()

    def leave(self, code: int) -> None:
        """End this process, which leaves before the sweep is complete, with exit status
        ``code``, skipping JAX's shutdown barrier (see the class); a no-op once
        ``"done"``."""
        self.stop("left")
        with self._lock:
            if self._state != "left":
                return
        if self.index == 0:  # serve the store until the others have ended
            deadline = time.monotonic() + self.grace_s + 5
            while time.monotonic() < deadline and self._others_running():
                time.sleep(self.poll_s)
        self._end(code)

    def _end(self, code: int) -> None:
        self._stop_keeper()
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass
        self._exit(code)
        self._stopped.set()  # (only reached with a test's ``exit``)

    def _stop_keeper(self) -> None:
        keeper, self._keeper = self._keeper, None
        if keeper is not None:
            try:
                keeper.kill()
                keeper.wait(5)
            except Exception:  # (already gone)
                pass

    def _set(self, value: str) -> None:
        self.client.key_value_set(f"{self.PREFIX}{self.index}", value, allow_overwrite=True)

    def _talk(self) -> None:
        while not self._stopped.is_set():
            try:
                with self._publish_lock:
                    with self._lock:
                        state, ending = self._state, self._ending
                    if ending is not None and not self._published.is_set():
                        self._set(f"stopped {ending}")
                        self._published.set()
                    elif state == "alive":
                        self._beats += 1
                        self._set(f"alive {self._beats}")
                entries = self.client.key_value_dir_get(self.PREFIX)
            except Exception as err:
                with self._lock:
                    self._errors += 1
                    self._error = (str(err).strip().splitlines() or [type(err).__name__])[0]
            else:
                now = time.monotonic()
                with self._lock:
                    self._errors, self._last_ok = 0, now
                    for key, value in entries:
                        tail = key.rpartition("/")[2]
                        j = int(tail) if tail.isdigit() else -1
                        if j in self._seen and self._seen[j][0] != value:
                            self._seen[j] = (value, now)
            self._stopped.wait(self.poll_s)

    def _verdict(self, now: float) -> str | None:
        with self._lock:
            if now - self._last_ok > self.timeout_s or self._errors >= 3:
                why = (self._error if self._errors else
                       f"no answer for {self.timeout_s:g} s")
                return f"lost the connection to the coordinator (process 0): {why}; {_RERUN}"
            for j, (value, since) in sorted(self._seen.items()):
                if value is None or value.startswith("alive"):
                    if self._last_ok - since > self.timeout_s:
                        return (f"process {j} stopped responding (no heartbeat for "
                                f"{self.timeout_s:g} s); {_RERUN}")
                elif value.startswith("stopped "):
                    return value[len("stopped "):]
                elif value == "left" and self._last_ok - since > self.grace_s:
                    return f"process {j} ended before the sweep was complete; {_RERUN}"
        return None

    def _others_running(self) -> bool:
        with self._lock:
            return any((value is None or value.startswith("alive"))
                       and self._last_ok - since <= self.timeout_s
                       for value, since in self._seen.values())

    def _judge(self) -> None:
        while not self._stopped.wait(self.poll_s):
            with self._lock:
                if self._state != "alive":
                    return
            message = self._verdict(time.monotonic())
            if message is None:
                continue
            with self._lock:
                if self._state != "alive":
                    return
                self._state, self._ending = "stopped", message
            self._published.wait(min(2.0, self.timeout_s))
            try:
                sys.stderr.flush()
            except Exception:
                pass
            try:  # (after a progress bar's unfinished line, on a new line)
                fresh = "\n" if sys.stderr is not None and sys.stderr.isatty() else ""
            except Exception:
                fresh = ""
            try:
                os.write(2, f"{fresh}{self.prog}: {message}\n".encode())
            except OSError:
                pass
            if self.index == 0:  # serve the store until the others have ended
                deadline = time.monotonic() + min(10.0, self.timeout_s)
                while time.monotonic() < deadline and self._others_running():
                    time.sleep(self.poll_s)
            self._end(self.exit_code)
            return


#: The keeper's program: wait for the parent (argv[1]) to end, then linger argv[2] s.
_KEEPER = ("import os, sys, time\n"
           "parent, linger = int(sys.argv[1]), float(sys.argv[2])\n"
           "while os.getppid() == parent:\n"
           "    time.sleep(0.2)\n"
           "time.sleep(linger)\n")


def _connected_sockets() -> list[int]:
    """This process's connected (not listening) socket descriptors; [] where they cannot
    be listed."""
    for folder in ("/proc/self/fd", "/dev/fd"):
        try:
            names = os.listdir(folder)
            break
        except OSError:
            continue
    else:
        return []
    fds = []
    for name in names:
        try:
            fd = int(name)
            if not stat.S_ISSOCK(os.fstat(fd).st_mode):
                continue
            with socket.socket(fileno=os.dup(fd)) as sock:
                if sock.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN):
                    continue  # the listening port: free it at once for a rerun
            fds.append(fd)
        except (OSError, ValueError):
            continue
    return fds


def _start_keeper(linger_s: float) -> subprocess.Popen | None:
    """Start a process that holds copies of this process's connected sockets until
    ``linger_s`` seconds after this process has ended (see :class:`Watchdog`); None if
    there are none or it cannot start."""
    fds = _connected_sockets()
    if not fds:
        return None
    try:
        return subprocess.Popen(
            [sys.executable, "-I", "-S", "-c", _KEEPER, str(os.getpid()), f"{linger_s:g}"],
            pass_fds=fds, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL, start_new_session=True)
    except OSError:
        return None


class Group:
    """The processes of one distributed call, through the coordinator's key-value store:
    ``publish``/``read`` JSON values, ``barrier``, a shared counter. Keys live under a
    prefix unique to the call (every process makes the same calls in the same order)."""

    _calls = 0
    #: Seconds a barrier or a read waits while another process may still be computing
    #: (a dead process ends the others through the :class:`Watchdog` long before).
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
