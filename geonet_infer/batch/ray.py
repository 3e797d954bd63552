"""The ``ray`` runner of ``geonet-infer batch``: Ray Data with an actor pool (extra ``geonet-infer[ray]``).

The work units (one per sequence) are a dataset (``ray.data.from_items``); ``map_batches``
sends them one at a time to an actor pool; each actor loads one predictor
(``num_cpus`` = its onnxruntime threads) and writes its sequences itself, with
:func:`geonet_infer.batch.run_sequence` (so the layout, the markers and the failure records
are those of the local runner). Only small JSON results come back to the driver.

Sizing: Ray Data deadlocks when read tasks and actors together ask for more CPUs than the
cluster has (``../shared/reference/onnx_notes.md`` section 4). ``from_items`` has no read
tasks (the items live in the driver's object store), and the pool is sized from the
cluster's CPUs, node by node: actors x threads never exceed them. Outputs must be on a file
system every node sees at the same path (a local cluster: this machine).
"""

from __future__ import annotations

import contextlib
import inspect
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import asdict
from pathlib import Path

import numpy as np

from geonet_infer.batch.units import (
    BatchConfig,
    WorkUnit,
    describe_error,
    discard,
    failed_result,
    plan_workers,
    read_marker,
    run_sequence,
)
from geonet_infer.engines import usable_cpus
from geonet_infer.errors import BackendUnavailableError, InputError

INSTALL_HINT = "pip install 'geonet-infer[ray]'"
LOCAL_OBJECT_STORE_BYTES = 256 * 1024**2  # results are a few hundred bytes a sequence


def import_ray():
    """``ray`` and ``ray.data``, or GeoNetError (exit 2) saying how to install them."""
    try:
        import ray
        import ray.data  # noqa: F401
    except ImportError as exc:
        raise BackendUnavailableError(
            None, f"--runner ray needs Ray Data, which is not installed ({exc})", INSTALL_HINT
        ) from None
    return ray


class _SequenceActor:
    """One predictor per actor; ``__call__`` predicts the batch's sequences and writes them.

    The job's config and options are class attributes of a subclass made per job
    (:func:`_actor_class`), not constructor arguments: Ray keeps those in the object store
    and warns that a restarted actor may not find them.
    """

    config: BatchConfig
    options: dict

    def __init__(self):
        from geonet_infer.core.predictor import load

        config = self.config
        self.predictor, self.error = None, None
        try:
            self.predictor = load(
                config.model, precision=config.precision, threads=config.threads, backend=config.backend
            )
        except Exception as exc:  # noqa: BLE001 - reported per sequence
            self.error = exc

    def __call__(self, batch: dict) -> dict:
        out = []
        for index, name, path, calib in zip(batch["index"], batch["name"], batch["path"], batch["calib"]):
            unit = WorkUnit(int(index), str(name), str(path), str(calib))
            if self.predictor is None:
                result = failed_result(unit, f"the actor could not load the model: {describe_error(self.error)}")
            else:
                result = run_sequence(unit, self.config, self.predictor, options=self.options)
            out.append(json.dumps(result))
        return {"result": np.array(out, dtype=object)}


def _actor_class(config: BatchConfig, options: dict) -> type:
    return type(
        "GeoNetSequenceActor", (_SequenceActor,), {"config": config, "options": options, "__module__": __name__}
    )


def _node_cpus(ray) -> list[int]:
    """CPUs of each alive node; their sum never above ``ray.cluster_resources()["CPU"]``
    (if the node list disagrees, the cluster total as one node)."""
    total = max(1, int(ray.cluster_resources().get("CPU", 1)))
    cpus = [int(n.get("Resources", {}).get("CPU", 0)) for n in ray.nodes() if n.get("Alive", n.get("alive"))]
    cpus = [c for c in cpus if c > 0]
    return cpus if cpus and sum(cpus) <= total else [total]


def size_pool(
    node_cpus: list[int], n_units: int, workers: int | None, threads: int | None
) -> tuple[int, int, str | None]:
    """(actors, threads per actor, note or None) that fit the nodes' CPUs.

    Actors x threads never exceed the CPUs (per node: an actor's CPUs are on one node);
    the default is :func:`geonet_infer.batch.plan_workers` on the cluster's CPUs.
    """
    total = sum(node_cpus)
    workers, threads = plan_workers(n_units, workers, threads, cpus=total)
    note = None
    if threads > max(node_cpus):
        note = f"{threads} threads per actor > {max(node_cpus)} CPUs of the largest node; using {max(node_cpus)}"
        threads = max(node_cpus)
    fit = sum(c // threads for c in node_cpus)
    if workers > fit:
        note = (
            f"{workers} actors x {threads} threads do not fit the cluster's {total} CPUs "
            f"(Ray Data would wait forever); using {fit} actors"
        )
        workers = fit
    return max(1, workers), threads, note


def check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail fast (GeoNetError) when a HOST:PORT or ray://HOST:PORT address does not answer:
    ``ray.init`` would retry for minutes. ``auto`` and other forms are left to Ray."""
    import socket

    rest = address[len("ray://") :] if address.startswith("ray://") else address
    host, sep, port = rest.rpartition(":")
    if not sep or not port.isdigit() or "/" in rest:
        return
    try:
        with socket.create_connection((host.strip("[]") or "127.0.0.1", int(port)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise InputError(
            None,
            f"cannot reach the Ray cluster at {address} ({exc.strerror or exc})",
            "is the cluster up (ray status)? check --ray-address",
        ) from None


class RayRunner:
    name = "ray"

    def __init__(
        self,
        ray,
        config: BatchConfig,
        options: dict,
        workers: int,
        threads: int,
        address: str | None,
        started_here: bool,
    ):
        self.ray, self.options = ray, options
        self.config = BatchConfig(**{**asdict(config), "camera": config.camera, "threads": threads})
        self.workers, self.threads, self.address, self._started_here = workers, threads, address, started_here
        self.limits: list[str] = []  # the pool is sized from the cluster's CPUs (size_pool notes it)
        self._frames = 0
        self._pending: list[WorkUnit] = []

    @classmethod
    def start(
        cls,
        config: BatchConfig,
        options: dict,
        n_units: int,
        workers: int | None,
        threads: int | None,
        *,
        manifest=None,
        address: str | None = None,
        log,
    ) -> RayRunner:
        """Start a local cluster (no address) or join ``address``, and size the actor pool."""
        if address:
            check_reachable(address)  # before anything needs ray: an unreachable cluster is the user's error to see
        ray = import_ray()
        started_here = False
        for name in ("ray", "ray.data"):  # Ray's notices (token auth on, progress bars off) are not ours to show
            logging.getLogger(name).setLevel(logging.ERROR)
        if not ray.is_initialized():
            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
            common = dict(logging_level=logging.ERROR, log_to_driver=True)
            # ray.init replaces the SIGTERM handler with sys.exit(15) (and its core worker adds a C++
            # stack dump): the job's own handler is put back, so SIGTERM stops the job like Ctrl-C.
            main_thread = threading.current_thread() is threading.main_thread()
            previous = signal.getsignal(signal.SIGTERM) if main_thread else None
            started = time.perf_counter()
            try:
                if address:
                    ray.init(address=address, **common)
                else:
                    ray.init(
                        address="local",
                        num_cpus=usable_cpus(),
                        include_dashboard=False,
                        object_store_memory=LOCAL_OBJECT_STORE_BYTES,
                        **common,
                    )
            except (ConnectionError, RuntimeError, ValueError) as exc:
                where = f"the Ray cluster at {address}" if address else "a local Ray cluster"
                raise InputError(
                    None,
                    f"cannot start or join {where} ({describe_error(exc).splitlines()[0]})",
                    "check --ray-address (e.g. ray://HOST:10001, HOST:6379 or auto)",
                ) from None
            except SystemExit as exc:  # Ray's handler: SIGTERM while the cluster was starting
                if exc.code != signal.SIGTERM:
                    raise
                with contextlib.suppress(Exception):
                    ray.shutdown()
                raise KeyboardInterrupt from None
            finally:
                if previous is not None:
                    signal.signal(signal.SIGTERM, previous)
            started_here = True
            # Ray's core worker then prints one "E ... core_worker.cc ... constructor arguments in the object
            # store" line per actor pool (Ray issue 57733): harmless, and said so before the user sees it
            log(
                f"geonet-infer batch: note: Ray {'joined' if address else 'local cluster up'} in "
                f"{time.perf_counter() - started:.1f} s; its 'core_worker.cc ... constructor arguments' "
                "error line is harmless (on one machine the local runner is faster: docs/runtime.md)"
            )
        ctx = ray.data.DataContext.get_current()
        for key, value in (
            ("enable_progress_bars", False),
            ("print_on_execution_start", False),
            ("enable_auto_log_stats", False),
        ):
            if hasattr(ctx, key):
                setattr(ctx, key, value)
        n_workers, n_threads, note = size_pool(_node_cpus(ray), n_units, workers, threads)
        if note:
            log(f"geonet-infer batch: note: {note}")
        return cls(ray, config, options, n_workers, n_threads, address, started_here)

    def live_frames(self) -> int:
        return self._frames

    def results(self, units: list[WorkUnit]) -> Iterator[dict | None]:
        ray = self.ray
        items = [asdict(u) for u in units]
        params = inspect.signature(ray.data.from_items).parameters
        blocks = {"override_num_blocks": len(items)} if "override_num_blocks" in params else {"parallelism": len(items)}
        ds = ray.data.from_items(items, **blocks)
        ds = ds.map_batches(
            _actor_class(self.config, self.options),
            batch_size=1,
            batch_format="numpy",
            num_cpus=self.threads,
            compute=ray.data.ActorPoolStrategy(size=self.workers),
        )
        returned: set[int] = set()
        self._pending = list(units)
        try:
            for row in ds.iter_rows():
                result = json.loads(row["result"])
                returned.add(result["index"])
                self._pending = [u for u in self._pending if u.index != result["index"]]
                self._frames += result["frames"]
                yield result
        except Exception as exc:  # noqa: BLE001 - e.g. an actor process died: the rest is reported, not lost
            reason = f"Ray Data stopped: {describe_error(exc).splitlines()[0][:300]}"
            for unit in units:
                if unit.index not in returned:
                    yield failed_result(unit, reason)

    def close(self) -> None:
        """Disconnect (and stop the cluster if this job started it): the job's actors end with it.

        Then remove the folders of sequences that did not come back and have no ``.done``
        (interrupted): best effort, as an actor may take a moment to die; --resume redoes them
        either way.
        """
        if self._started_here and self.ray.is_initialized():
            self.ray.shutdown()
        for unit in self._pending:
            folder = Path(self.config.out_dir) / unit.name
            if read_marker(folder) is None:
                with contextlib.suppress(Exception):
                    discard(folder)
        self._pending = []
