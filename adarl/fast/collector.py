"""A lean single-process collector for SAC's TanhNormal policy: TorchRL's ``Collector`` without its per-step cost.

Why: with one env on CPU, ``torchrl.collectors.Collector`` spends ~0.6 ms per frame in TensorDict and
policy-wrapper bookkeeping on top of the environment itself (docs/performance.md). :class:`LeanCollector`
steps the same TorchRL env (transforms, perturbations and all) with ``env.step_and_maybe_reset`` and samples
the action straight from the actor's network: ``tanh(loc + scale * eps)`` (then scaled to the action box),
the same distribution the ``ProbabilisticActor`` samples from in ``ExplorationType.RANDOM``. Batches carry the
keys the replay buffer and the training loop read (``observation``, ``action``, ``("next", ...)`` with reward,
done flags and the env's own extra keys). On an env :func:`adarl.envs.make_env` builds for one environment, the
in-episode steps skip TorchRL's env wrapper too (:mod:`adarl.fast.direct_env`: the gymnasium env is stepped directly
and the frames written into the batch's tensors, bit-identical to TorchRL's; resets stay TorchRL's).

With ``overlap`` the next batch is collected while the caller trains on the current one, in a thread
(``"thread"``) or in a worker process (``"process"``: a second core, no GIL shared with the updates). Both hand
out bit-identical batches: the worker gets the policy snapshot, the noise generator and the env's full live
state (simulator, gymnasium counters and RNG, perturbation state, TorchRL carrier; the exact-resume snapshot of
:mod:`adarl.envs.state`), steps its own copy of the env, and sends the same state back, which is loaded into the
caller's env when something needs it (``drain``, ``reset``, ``state_dict``), so that env is then where a
synchronous collector would have left it.

Mirrors: ``torchrl.collectors.Collector`` (one env, ``frames_per_batch``, ``init_random_frames``, a
``ProbabilisticActor`` in ``ExplorationType.RANDOM``) for the keys a replay buffer and the trainers read.
Equality: ``tests/test_lean_collector.py::test_batches_equal_torchrl_collectors`` (the same batches as TorchRL's
``Collector`` from the same seeds) and
``tests/test_lean_collector.py::test_policy_action_equals_probabilistic_actor_sample``; the overlap modes against each
other in ``tests/test_lean_collector.py`` and ``tests/test_kill_resume.py``.
"""

from __future__ import annotations

import copy
import copyreg
import io
import multiprocessing
import pickle
import threading
import traceback
import weakref
from collections.abc import Callable, Iterator

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import NormalParamExtractor
from torchrl.modules import MLP

from adarl.envs.factory import dynamics_state_dict, load_dynamics_state_dict
from adarl.envs.state import env_state_dict, load_env_state_dict
from adarl.errors import AdaRLValueError
from adarl.fast import _torch_private as private
from adarl.fast.direct_env import DirectStepper, direct_stepper

__all__ = ["LeanCollector", "wants_lean", "OVERLAP_MODES"]

OVERLAP_MODES = (False, "thread", "process")


def _is_tanh_normal_actor(policy) -> bool:
    first = getattr(policy, "module", [None])[0]
    net = getattr(first, "module", None)
    return isinstance(net, torch.nn.Sequential) and isinstance(net[-1], NormalParamExtractor)


def wants_lean(setting, env, policy) -> bool:
    """Resolve ``collector.lean``: ``'auto'`` is on for one env and a TanhNormal actor; ``True`` insists."""
    ok = tuple(env.batch_size) == () and _is_tanh_normal_actor(policy)
    if setting == "auto":
        return ok
    if setting is True and not ok:
        raise AdaRLValueError(
            "collector.lean: true needs one env (env.num_envs: 1) and a TanhNormal (box-action) "
            "actor; allowed otherwise: 'auto' or false"
        )
    return bool(setting)


class LeanCollector:
    """Iterate batches of ``frames_per_batch`` transitions from ``env`` under ``policy`` (uniform-random first).

    Args:
        env: a TorchRL env with a batch size of ``[]`` (one environment).
        policy: a ``ProbabilisticActor`` built by :func:`adarl.runtime.builders.make_sac_actor` for a box action space.
        frames_per_batch: transitions per yielded batch.
        init_random_frames: frames of uniform-random actions before the policy acts.
        total_frames: stop after this many frames; ``-1`` never stops (as the Trainer uses it).
        overlap: ``False``; ``"thread"`` (or ``True``) or ``"process"``: collect the next batch in the
            background while the caller trains on the current one. The background collector acts with a copy of
            the actor network taken when the current batch is handed over, so batch ``k + 1`` comes from the
            policy after the updates of batch ``k - 1`` (one batch staler than without overlap, like TorchRL's
            asynchronous collectors); its action noise comes from its own generator (``noise_seed``). The random
            phase is never overlapped. Deterministic: the result does not depend on timing, both modes hand out
            the same batches, and :meth:`state_dict` keeps a finished prefetched batch for exact resume.
        noise_seed: seed of that generator (overlap only).
        env_factory: ``"process"`` only: a picklable callable that builds an env like ``env`` (its seed does
            not matter: the worker's env is given ``env``'s live state whenever it is not already in it), e.g.
            ``functools.partial(adarl.envs.make_env, "Hopper-v5", preset="paper")``. The worker is a ``spawn``ed
            process started at the first overlapped batch and stopped by :meth:`shutdown` (or when the collector
            is garbage-collected, or when this process dies).
        direct: ``"auto"`` steps the gymnasium env directly where :mod:`adarl.fast.direct_env` reproduces the env's
            TorchRL frames exactly (a single-env :func:`adarl.envs.make_env` env), else through TorchRL; ``True``
            insists (raises for other envs); ``False`` always steps through TorchRL. The batches are the same
            either way; :attr:`direct` tells which path is used (the ``"process"`` worker uses the same).
    """

    def __init__(
        self,
        env,
        policy,
        *,
        frames_per_batch: int,
        init_random_frames: int = 0,
        total_frames: int = -1,
        overlap: bool | str = False,
        noise_seed: int = 0,
        env_factory: Callable[[], object] | None = None,
        direct: bool | str = "auto",
    ) -> None:
        if tuple(env.batch_size) != ():
            raise AdaRLValueError(
                f"LeanCollector runs one env (batch_size []), got batch_size {tuple(env.batch_size)}; "
                "set collector.lean: false for vectorised envs"
            )
        if not _is_tanh_normal_actor(policy):
            raise AdaRLValueError(
                "LeanCollector needs a TanhNormal actor from adarl.runtime.builders.make_sac_actor; "
                "set collector.lean: false"
            )
        if frames_per_batch < 1:
            raise AdaRLValueError(f"frames_per_batch must be >= 1, got {frames_per_batch}")
        self.env, self.policy, self.net = env, policy, policy.module[0].module
        self.frames_per_batch = int(frames_per_batch)
        self.init_random_frames = int(init_random_frames)
        self.total_frames = int(total_frames)
        kw = policy.module[1].distribution_kwargs
        low = torch.as_tensor(kw.get("low", -1.0), dtype=torch.float32)
        high = torch.as_tensor(kw.get("high", 1.0), dtype=torch.float32)
        self._box = ((high + low) / 2, (high - low) / 2, bool((low != -1).any() or (high != 1).any()))
        self.frames = 0
        self._td: TensorDictBase | None = None
        self._stepper = direct_stepper(env, direct)
        self.direct = self._stepper is not None
        if overlap is True:
            overlap = "thread"
        if overlap not in OVERLAP_MODES:
            raise AdaRLValueError(f"overlap must be one of {OVERLAP_MODES} (True means 'thread'), got {overlap!r}")
        if overlap == "process" and not callable(env_factory):
            raise AdaRLValueError(
                "overlap='process' needs env_factory: a picklable callable that builds the same env "
                "(e.g. functools.partial(adarl.envs.make_env, env_id, preset=...)); "
                "or use overlap='thread'"
            )
        self.mode = overlap
        self.overlap = overlap is not False
        self.env_factory = env_factory
        self._noise = torch.Generator().manual_seed(int(noise_seed)) if self.overlap else None
        self._thread: threading.Thread | None = None
        self._result: dict = {}
        self._ready: TensorDictBase | None = None
        self._worker: _Worker | None = None
        self._pending = False  # a job was sent to the worker and its answer not yet read
        self._unsynced: dict | None = None  # the worker's final env state, not yet loaded into ``env``

    def reset(self) -> None:
        """Start a fresh episode at the next step (call after anything else stepped or reset the env).

        A batch being prefetched is finished and dropped (its frames are not counted): it continued the
        episode that is being abandoned."""
        self.drain(keep=False)
        self._td = None

    @torch.no_grad()
    def act(self, td: TensorDictBase, net=None, generator: torch.Generator | None = None) -> torch.Tensor:
        """One action: uniform-random during the random phase, else a TanhNormal sample from the policy."""
        return self._act(td.get("observation"), self.frames, self.net if net is None else net, generator)

    def _act(self, obs: torch.Tensor, frame: int, net, generator: torch.Generator | None) -> torch.Tensor:
        if frame < self.init_random_frames:
            return self.env.action_spec.rand()
        return _tanh_normal_action(net, obs, generator, self._box)

    def _collect(self, net=None, generator: torch.Generator | None = None) -> TensorDictBase:
        start, forward = self.frames, _layer_chain(self.net if net is None else net)
        try:
            with torch.no_grad():
                batch, self._td = _rollout(
                    self.env,
                    self._stepper,
                    self._td,
                    self.frames_per_batch,
                    lambda obs, i: self._act(obs, start + i, forward, generator),
                )
        except BaseException:
            self._td = None  # the env moved on from the carrier: a later batch starts a fresh episode
            raise
        self.frames += self.frames_per_batch
        return batch

    def rollout(self) -> TensorDictBase:
        """One batch of ``frames_per_batch`` frames from the current policy, here and now, outside the iteration.

        What :class:`~adarl.core.warmstart.ReplayWarmStart` collects after a rank event (the contract of
        ``torchrl.collectors.Collector.rollout``): a batch being prefetched is finished and kept first, so the
        frames come from the env where the iteration left it (call :meth:`reset` before for fresh episodes, as the
        warm start does). The frames do not count towards :attr:`frames` (the random phase and ``total_frames``
        belong to the iteration); the policy acts unless ``init_random_frames`` is above the frames collected so
        far (the warm start sets it to 0 while it collects). Synchronous in every ``overlap`` mode, on the caller's
        env, with the global RNG, like TorchRL's env rollout this replaces (about 3x faster a frame on Hopper).
        """
        self.drain(keep=True)
        frames = self.frames
        try:
            return self._collect(None, None)
        finally:
            self.frames = frames

    def _prefetch(self) -> None:
        """Start collecting the next batch in the background with a snapshot of the current policy."""
        if self.mode == "process":
            self._prefetch_remote()
            return
        snapshot = copy.deepcopy(self.net)
        self._result = {}

        def work():
            try:
                self._result["batch"] = self._collect(snapshot, self._noise)
            except BaseException as err:  # re-raised in the caller's thread by drain()
                self._result["error"] = err

        self._thread = threading.Thread(target=work, name="adarl-lean-collector", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ the worker process ("process" mode)
    def _prefetch_remote(self) -> None:
        if self._worker is None or not self._worker.alive():
            self._sync_env()  # a new worker knows no state: it gets the caller's
            self._worker = _Worker(self.env_factory, self.direct)
        w = self._worker
        job = {"noise": self._noise.get_state(), "n": self.frames_per_batch, "box": self._box}
        # The env: None when the caller's env was not synced since the last reply (the worker's env is still
        # where that batch left it), else the caller's live state.
        job["state"] = None if self._unsynced is not None else _snapshot(self.env, self._td)
        # The policy: the whole module when its layout changed (a rank event), else its parameters only.
        layout = tuple((k, tuple(v.shape), v.dtype) for k, v in self.net.state_dict().items())
        if layout != w.layout:
            job["net"], w.layout = self.net, layout
        else:
            job["params"] = [v.detach() for v in self.net.state_dict().values()]
        w.send(job)
        self._pending = True

    def _receive_remote(self) -> TensorDictBase:
        self._pending = False
        out = self._worker.receive()
        self._unsynced = out["state"]  # loaded into the caller's env only when something needs it (_sync_env)
        self._noise.set_state(out["noise"])
        self.frames += self.frames_per_batch
        return TensorDict(out["batch"], batch_size=out["batch_size"])

    def _sync_env(self) -> None:
        """Put the worker's final env state into the caller's env (where a synchronous collector leaves it)."""
        if self._unsynced is None:
            return
        state, self._unsynced = self._unsynced, None
        self._td = _restore(self.env, state)

    def _finish_prefetch(self, keep: bool) -> None:
        if self._pending:
            self._ready = self._receive_remote()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
            if "error" in self._result:
                raise self._result.pop("error")
            self._ready = self._result.pop("batch")
        if not keep and self._ready is not None:
            self.frames -= self._ready.numel()
            self._ready = None

    def drain(self, keep: bool = True) -> None:
        """Wait for a batch being prefetched; keep it for the next iteration, or drop it (``keep=False``).

        Afterwards the env is where a synchronous collector would have left it (the worker's state is loaded)."""
        self._finish_prefetch(keep)
        self._sync_env()

    def __iter__(self) -> Iterator[TensorDictBase]:
        while (
            self.total_frames < 0
            or self.frames < self.total_frames
            or self._ready is not None
            or self._thread is not None
            or self._pending
        ):
            self._finish_prefetch(keep=True)  # the env is synced only when something needs it
            if self._ready is not None:
                batch, self._ready = self._ready, None
            else:
                self._sync_env()
                batch = self._collect(None, self._noise)  # the overlap's generator is used from the start
            more = self.total_frames < 0 or self.frames < self.total_frames
            if self.overlap and more and self.frames >= self.init_random_frames:
                self._prefetch()
            yield batch

    def state_dict(self) -> dict:
        """Frame counter and the live step's TensorDict (the carrier), for exact resume.

        With ``overlap`` a batch being prefetched is finished first and saved with the noise generator's state,
        so a resumed run hands out the same batch next."""
        self.drain(keep=True)
        state = {
            "frames": self.frames,
            "iter": 0,
            "traj_pool": None,
            "carrier": None if self._td is None else self._td.to_dict(),
            "carrier_batch_size": [] if self._td is None else list(self._td.batch_size),
        }
        if self.overlap:
            state["prefetched"] = None if self._ready is None else self._ready.to_dict()
            state["prefetched_batch_size"] = None if self._ready is None else list(self._ready.batch_size)
            state["noise_rng"] = self._noise.get_state()
        return state

    def load_state_dict(self, state: dict, *, carrier: bool = True) -> None:
        self._finish_prefetch(keep=False)
        self._unsynced = None  # the caller restores the env itself (the Trainer does, before this)
        self.frames = int(state["frames"])
        if carrier and state.get("carrier") is not None:
            self._td = TensorDict(state["carrier"], batch_size=state["carrier_batch_size"])
        else:
            self._td = None
        if self.overlap:
            if state.get("noise_rng") is not None:
                self._noise.set_state(state["noise_rng"])
            if carrier and state.get("prefetched") is not None:
                self._ready = TensorDict(state["prefetched"], batch_size=state["prefetched_batch_size"])
            elif state.get("prefetched") is not None:  # the episode is not restored: drop its continuation too
                self.frames -= int(state["prefetched_batch_size"][0])

    def shutdown(self) -> None:
        """Finish and drop a batch being prefetched and stop the worker process; nothing runs in the background.

        The collector can still be iterated afterwards (a new worker is started when needed)."""
        try:
            self.drain(keep=False)
        finally:
            self._td = None
            if self._worker is not None:
                self._worker.close()
                self._worker = None


def _snapshot(env, td: TensorDictBase | None) -> dict:
    """The env's live state (perturbation, simulator and gymnasium state, TorchRL carrier), as a checkpoint has it."""
    return {
        "dynamics": dynamics_state_dict(env),
        "env": env_state_dict(env),
        "carrier": None if td is None else (td.to_dict(), list(td.batch_size)),
    }


def _restore(env, state: dict) -> TensorDictBase | None:
    """Put a :func:`_snapshot` back into ``env``; returns the carrier TensorDict (None: the next step resets)."""
    load_dynamics_state_dict(env, state["dynamics"])
    load_env_state_dict(env, state["env"])
    carrier = state["carrier"]
    return None if carrier is None else TensorDict(carrier[0], batch_size=carrier[1])


def _tanh_normal_action(net, obs: torch.Tensor, generator: torch.Generator | None, box: tuple) -> torch.Tensor:
    """``tanh(loc + scale * eps)`` scaled to the action box ``(mid, half, affine)``: the policy's random action."""
    mid, half, affine = box
    loc, scale = net(obs)
    eps = torch.randn_like(loc) if generator is None else torch.randn(loc.shape, generator=generator)
    action = torch.tanh(loc + scale * eps)
    return action * half + mid if affine else action


def _layer_chain(net: torch.nn.Module) -> Callable[[torch.Tensor], object]:
    """``net`` as the chain of its layers' ``forward`` methods: the same operations in the same order, without the
    containers' and ``Module.__call__``'s Python overhead (~20 us of the ~125 us a (64, 64) actor's action takes
    on one observation). ``net`` itself where a hook is registered or a container does more than chain its children
    (and on a torch whose hook tables :mod:`adarl.fast._torch_private` does not know)."""

    if private.global_module_hooks():
        return net
    layers = []

    def add(m: torch.nn.Module) -> bool:
        if private.module_hooked(m):
            return False
        if type(m) is torch.nn.Sequential or (type(m) is MLP and not m._reshape_out):
            return all(add(child) for child in m)
        layers.append(m.forward)  # a layer's own children are called the usual way (their hooks run)
        return True

    if not add(net):
        return net

    def forward(x):
        for layer in layers:
            x = layer(x)
        return x

    return forward


def _rollout(
    env,
    stepper: DirectStepper | None,
    td: TensorDictBase | None,
    n: int,
    act: Callable[[torch.Tensor, int], torch.Tensor],
) -> tuple[TensorDictBase, TensorDictBase]:
    """``n`` frames from the carrier ``td`` (None: reset first), ``act(observation, i)`` choosing frame ``i``'s
    action: the batch and the next carrier. Directly when ``stepper`` continues ``td`` exactly, else through TorchRL."""
    if stepper is not None and (td is None or stepper.accepts(td)):
        return stepper.rollout(td, n, act)
    steps = []
    for i in range(n):
        if td is None:
            td = env.reset()
        td.set("action", act(td.get("observation"), i))
        out, td = env.step_and_maybe_reset(td)
        steps.append(out)
    return torch.stack(steps).contiguous(), td


def _collect_remote(env, stepper: DirectStepper | None, net, job: dict) -> tuple[dict, TensorDictBase | None]:
    """One batch in the worker: (load the caller's live state,) step ``job["n"]`` times; the reply and the carrier."""
    # the env is still where this worker's previous batch left it when the job carries no state
    td = job["_carrier"] if job["state"] is None else _restore(env, job["state"])
    noise = torch.Generator()
    noise.set_state(job["noise"])
    forward = _layer_chain(net)
    with torch.no_grad():
        batch, td = _rollout(
            env, stepper, td, job["n"], lambda obs, i: _tanh_normal_action(forward, obs, noise, job["box"])
        )
    return {
        "batch": batch.to_dict(),
        "batch_size": list(batch.batch_size),
        "noise": noise.get_state(),
        "state": _snapshot(env, td),
    }, td


def _worker_main(conn, env_factory, direct: bool) -> None:
    """The worker process: build the env once, then answer one collection job per message until told to stop."""
    torch.set_num_threads(1)
    try:
        env = env_factory()
        stepper = direct_stepper(env, "auto" if direct else False)  # the caller's path, where this env allows it
    except BaseException:
        conn.send_bytes(_dumps(("error", traceback.format_exc())))
        return
    net, carrier = None, None
    while True:
        try:
            msg = conn.recv_bytes()
        except (EOFError, OSError):  # the caller is gone
            return
        job = pickle.loads(msg)
        if job is None:
            return
        try:
            if "net" in job:
                net = job["net"]
            else:
                with torch.no_grad():
                    for p, v in zip(net.state_dict().values(), job["params"]):
                        p.copy_(v)
            job["_carrier"] = carrier
            out, carrier = _collect_remote(env, stepper, net, job)
            reply = ("ok", out)
        except BaseException:
            reply = ("error", traceback.format_exc())
        try:
            conn.send_bytes(_dumps(reply))
        except (BrokenPipeError, OSError):  # the caller died while this batch was collected
            return


def _tensor_as_numpy(t: torch.Tensor):
    """Pickle a CPU tensor as a numpy array. Why: torch's own reduction runs a ``torch.save`` per storage; a
    50-frame Hopper batch plus the actor took 5.6 ms to pickle and unpickle that way, 0.7 ms this way."""
    if t.device.type != "cpu" or t.dtype not in _NUMPY_DTYPES or type(t) not in (torch.Tensor, torch.nn.Parameter):
        return t.__reduce_ex__(pickle.HIGHEST_PROTOCOL)
    array = t.detach().contiguous().numpy()
    if type(t) is torch.nn.Parameter:
        return _parameter_from_numpy, (array, t.requires_grad)
    return torch.from_numpy, (array,)


def _parameter_from_numpy(array, requires_grad: bool) -> torch.nn.Parameter:
    return torch.nn.Parameter(torch.from_numpy(array), requires_grad=requires_grad)


_NUMPY_DTYPES = {
    torch.float32,
    torch.float64,
    torch.float16,
    torch.int64,
    torch.int32,
    torch.int16,
    torch.int8,
    torch.uint8,
    torch.bool,
}


def _dumps(obj) -> bytes:
    buf = io.BytesIO()
    pickler = pickle.Pickler(buf, protocol=pickle.HIGHEST_PROTOCOL)
    pickler.dispatch_table = {
        **copyreg.dispatch_table,
        torch.Tensor: _tensor_as_numpy,
        torch.nn.Parameter: _tensor_as_numpy,
    }
    pickler.dump(obj)
    return buf.getvalue()


class _Worker:
    """A spawned collection process and its pipe (messages are pickled by hand: no shared-memory tensors)."""

    def __init__(self, env_factory, direct: bool) -> None:
        ctx = multiprocessing.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.layout: tuple | None = None  # the policy layout the worker holds (None: send the module)
        self.proc = ctx.Process(
            target=_worker_main,
            args=(child, env_factory, direct),
            name="adarl-lean-collector",
            daemon=not multiprocessing.current_process().daemon,
        )
        self.proc.start()
        child.close()
        self._finalizer = weakref.finalize(self, _stop_worker, self.conn, self.proc)

    def alive(self) -> bool:
        return self.proc.is_alive()

    def send(self, job: dict) -> None:
        try:
            self.conn.send_bytes(_dumps(job))
        except (BrokenPipeError, OSError) as err:
            raise RuntimeError(f"the collector worker process is gone (exit code {self.proc.exitcode})") from err

    def receive(self) -> dict:
        try:
            status, payload = pickle.loads(self.conn.recv_bytes())
        except (EOFError, OSError) as err:
            self.proc.join(timeout=5)
            raise RuntimeError(
                f"the collector worker process died (exit code {self.proc.exitcode}); its output is "
                "above. It is started with 'spawn', which imports your main script again: guard the "
                "script's code with `if __name__ == '__main__':`. Or set collector.overlap: 'thread' "
                "or false to collect in this process"
            ) from err
        if status == "error":
            raise RuntimeError(f"the collector worker process failed:\n{payload}")
        return payload

    def close(self) -> None:
        self._finalizer()


def _stop_worker(conn, proc) -> None:
    try:
        conn.send_bytes(pickle.dumps(None))
    except (OSError, ValueError):
        pass
    proc.join(timeout=5)
    if proc.is_alive():
        proc.terminate()
        proc.join(timeout=5)
    conn.close()
