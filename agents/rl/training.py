"""Reinforcement learning on filtered beliefs with stable-baselines3 (PPO and SAC).

An agent is saved as ``<out>/model.zip`` (SB3) with ``<out>/agent.json`` describing how
to rebuild its observations (variant, task, filter, model kind, model folder), so that
``evaluate_agent`` and ``gpbf collect --agent`` reproduce its inputs; an agent trained with
``normalize`` also has SB3's ``<out>/vecnormalize.pkl`` (its observation statistics, as
rl-zoo3 saves them).
"""

from __future__ import annotations

import json
import math
import os
import platform
import re
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3 import PPO, SAC
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback, EvalCallback
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv, VecMonitor, VecNormalize

from agents.rl.batched import BeliefVecEnv
from agents.rl.hyperparams import Hyperparams, load_hyperparams
from agents.rl.registry import TASK_ENVS, agent_env_id, episode_success
from agents.rl.wrappers import VARIANTS, make_belief_env
from estimator_service.files import atomic_write_text
from estimator_service.provenance import named_argv

__all__ = [
    "AgentPolicy",
    "AgentSpec",
    "agent_folder",
    "evaluate_agent",
    "evaluate_pilot",
    "latest_checkpoint",
    "load_agent",
    "make_vec",
    "observation_normalizer",
    "train_agent",
]

ALGOS: dict[str, type[BaseAlgorithm]] = {"ppo": PPO, "sac": SAC}
NORMALIZER_FILE = "vecnormalize.pkl"  # SB3's VecNormalize statistics, rl-zoo3's file name
CHECKPOINTS = "checkpoints"  # the folder of periodic snapshots inside an agent's folder
RUN_FILE = "run.json"  # how an agent was trained: command line, settings, package versions
_CHECKPOINT = re.compile(r"agent_(\d+)_steps\.zip")  # SB3 CheckpointCallback's model file names
_VERSIONED = ("gpbf", "numpy", "scipy", "torch", "stable_baselines3", "gymnasium")


@dataclass(frozen=True)
class AgentSpec:
    """Everything needed to rebuild an agent's environment."""

    algo: str = "ppo"
    variant: str = "belief"
    task: str = "hover"
    filter: str = "ekf"
    model: str = "gp"
    models: str | None = None
    seed: int = 0

    def __post_init__(self) -> None:
        if self.algo not in ALGOS:
            raise ValueError(f"algo must be one of {sorted(ALGOS)}, got {self.algo!r}")
        if self.variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {self.variant!r}")
        if self.task not in TASK_ENVS:
            raise ValueError(f"task must be one of {sorted(TASK_ENVS)}, got {self.task!r}")


def make_env(spec: AgentSpec, rank: int = 0, backend: str = "inprocess", client: Any = None):
    """One monitored env of ``spec`` (sub-env ``rank`` gets its own filter or session)."""
    env = make_belief_env(
        spec.variant,
        env_id=TASK_ENVS[spec.task],
        models=spec.models,
        filter=spec.filter,
        model=spec.model,
        backend=backend,
        client=client,
        seed=spec.seed + rank,
    )
    return Monitor(env)


def make_vec(
    spec: AgentSpec,
    n_envs: int = 1,
    backend: str = "inprocess",
    client: Any = None,
    batched: bool | None = None,
) -> VecEnv:
    """SB3 vector env of ``n_envs`` independent belief envs, seeded ``spec.seed + rank``.

    ``batched`` (the default for the in-process back end) steps the blimps in the native
    batched simulator and their filters with one batched model call
    (:class:`~agents.rl.batched.BeliefVecEnv`); otherwise a ``DummyVecEnv`` of
    :func:`make_env` envs steps them one at a time (the service back end always does).
    """
    batched = backend == "inprocess" if batched is None else batched
    if batched and backend != "inprocess":
        raise ValueError(f"batched belief envs run the filters in-process, not with backend {backend!r}")
    if batched:
        env = BeliefVecEnv(
            spec.variant, n_envs, env_id=TASK_ENVS[spec.task], models=spec.models, filter=spec.filter,
            model=spec.model,
        )  # fmt: skip
        venv: VecEnv = VecMonitor(env)
    else:
        venv = DummyVecEnv([lambda r=r: make_env(spec, r, backend, client) for r in range(n_envs)])
    venv.seed(spec.seed)
    return venv


SMALL = {  # tiny budgets (smoke tests): updates early enough to run in a few hundred steps
    "ppo": {"n_steps": 64, "batch_size": 64, "n_epochs": 2},
    "sac": {"learning_starts": 64, "batch_size": 64, "buffer_size": 10_000},
}


def _algo(
    spec: AgentSpec, venv: VecEnv, params: Hyperparams, small: bool, tensorboard: str | None
) -> BaseAlgorithm:
    kw = SMALL[spec.algo] if small else params.kwargs
    return ALGOS[spec.algo](
        params.policy, venv, seed=spec.seed, verbose=0, device="cpu", tensorboard_log=tensorboard, **kw
    )


class _Checkpoints(CheckpointCallback):
    """SB3's checkpoints with the replay buffer and normaliser statistics of the newest one
    only (a replay buffer is up to hundreds of MB; a resumed run needs the last)."""

    def _on_step(self) -> bool:
        done = super()._on_step()
        if self.n_calls % self.save_freq == 0:
            newest = f"_{self.num_timesteps}_steps.pkl"
            for f in Path(self.save_path).glob("agent_*_steps.pkl"):
                if not f.name.endswith(newest):
                    f.unlink(missing_ok=True)
        return done


def latest_checkpoint(folder: str | Path, companions: tuple[str, ...] = ()) -> tuple[Path, int] | None:
    """The newest checkpoint model in an agent folder's ``checkpoints/`` whose companion files
    ``agent_<companion>_<steps>_steps.pkl`` all exist (a run that stopped while saving one
    leaves a newer, incomplete checkpoint), and its steps; None when there is none."""
    found = [(int(m.group(1)), f) for f in (Path(folder) / CHECKPOINTS).glob("agent_*_steps.zip")
             if (m := _CHECKPOINT.fullmatch(f.name))]  # fmt: skip
    for steps, path in sorted(found, reverse=True):
        if all((path.parent / f"agent_{c}_{steps}_steps.pkl").is_file() for c in companions):
            return path, steps
    return None


def _versions(code: str | None = None) -> dict[str, str]:
    from estimator_service.provenance import code_version

    out = {"code": code or code_version(), "python": platform.python_version()}
    for name in _VERSIONED:
        try:
            out[name] = metadata.version(name.replace("_", "-"))
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def train_agent(
    spec: AgentSpec,
    timesteps: int | None,
    out_dir: str | Path,
    *,
    n_envs: int | None = None,
    eval_freq: int = 5000,
    eval_episodes: int = 3,
    progress_bar: bool = True,
    small: bool | None = None,
    hyperparams: str | Path | None = None,
    tensorboard: str | Path | None = None,
    checkpoint_freq: int | None = None,
    resume: bool = False,
    command: Sequence[str] | None = None,
    code: str | None = None,
) -> Path:
    """Train, evaluate periodically, checkpoint, save the model, the spec and a learning curve.

    Hyperparameters are the entry of the agent's registered id in ``hyperparams``
    (default ``hyperparams/<algo>.yml``); ``timesteps`` and ``n_envs`` default to the
    entry's. ``small`` (default: ``timesteps <= 5000``) uses :data:`SMALL` and one env
    instead, for smoke runs. ``tensorboard`` is a folder for SB3's TensorBoard logs (needs the
    ``tensorboard`` package). Every ``eval_freq`` steps ``eval_episodes`` episodes are
    evaluated (the learning curve, ``evaluations.npz``); every ``checkpoint_freq`` steps
    (default ``5 * eval_freq``) a checkpoint is kept in ``checkpoints/``, the newest with
    its replay buffer and normaliser statistics. With ``resume`` a run continues from the
    newest checkpoint of ``out_dir`` (its model, replay buffer, statistics and the learning
    curve up to it) to ``timesteps`` in all; the envs restart their episodes, so a resumed
    run is not step-for-step the uninterrupted one. ``out_dir/run.json`` records the command
    line (``command``, default ``sys.argv``), these settings and the package versions with
    the code version (``code``, default the checkout's now: an experiment passes the one it
    started with, since its worker processes run the code they imported then).
    """
    params = load_hyperparams(spec.algo, agent_env_id(spec.task, spec.variant), hyperparams)
    timesteps = params.n_timesteps if timesteps is None else timesteps
    small = timesteps <= 5000 if small is None else small
    n_envs = (1 if small else params.n_envs) if n_envs is None else n_envs
    if tensorboard is not None:
        import importlib.util

        if importlib.util.find_spec("tensorboard") is None:
            raise ModuleNotFoundError(
                "tensorboard logging needs the tensorboard package: pip install tensorboard"
            )
    checkpoint_freq = 5 * eval_freq if checkpoint_freq is None else checkpoint_freq
    if not (isinstance(checkpoint_freq, int) and checkpoint_freq >= 1):
        raise ValueError(f"checkpoint_freq must be a positive integer, got {checkpoint_freq!r}")
    out = Path(out_dir)
    needs = ("replay_buffer",) if hasattr(ALGOS[spec.algo], "load_replay_buffer") else ()
    needs += ("vecnormalize",) if params.normalize is not None else ()
    start = latest_checkpoint(out, needs) if resume else None
    if resume and start is None:
        raise FileNotFoundError(
            f"resume: no complete checkpoint in {os.fspath(out / CHECKPOINTS)!r} to continue from"
        )
    out.mkdir(parents=True, exist_ok=True)
    venv = make_vec(spec, n_envs)
    eval_env = make_vec(AgentSpec(**{**asdict(spec), "seed": spec.seed + 10_000}), 1)
    if params.normalize is not None:  # the eval env takes the training statistics (EvalCallback)
        gamma = float(params.kwargs.get("gamma", 0.99))
        venv = VecNormalize(venv, gamma=gamma, **params.normalize)
        eval_env = VecNormalize(
            eval_env, training=False, norm_obs=params.normalize["norm_obs"], norm_reward=False
        )
    if start is not None:
        venv, agent = _resumed(spec, venv, start, tensorboard)
    else:
        agent = _algo(spec, venv, params, small, None if tensorboard is None else str(tensorboard))
    evaluate = EvalCallback(
        eval_env,
        n_eval_episodes=eval_episodes,
        eval_freq=max(1, eval_freq // n_envs),
        log_path=str(out),
        best_model_save_path=None,
        deterministic=True,
        verbose=0,
    )
    if start is not None:
        _keep_curve(evaluate, out, start[1])
    settings = {"timesteps": timesteps, "n_envs": n_envs, "eval_freq": eval_freq,
                "eval_episodes": eval_episodes, "checkpoint_freq": checkpoint_freq, "small": small,
                "hyperparams": None if hyperparams is None else os.fspath(hyperparams)}  # fmt: skip
    _record_run(out, {"command": named_argv(command), "spec": asdict(spec),
                      **settings, "resumed_from_steps": None if start is None else start[1],
                      "versions": _versions(code)})  # fmt: skip
    checkpoints = _Checkpoints(
        save_freq=max(1, checkpoint_freq // n_envs), save_path=str(out / CHECKPOINTS), name_prefix="agent",
        save_replay_buffer=True, save_vecnormalize=True,
    )  # fmt: skip
    remaining = timesteps if start is None else max(0, timesteps - agent.num_timesteps)
    agent.learn(remaining, callback=CallbackList([evaluate, checkpoints]), progress_bar=progress_bar,
                reset_num_timesteps=start is None)  # fmt: skip
    agent.save(out / "model.zip")
    if isinstance(venv, VecNormalize):
        venv.save(out / NORMALIZER_FILE)
    atomic_write_text(out / "agent.json", json.dumps(asdict(_relative_models(spec, out)), indent=2))
    _plot_learning_curve(out)
    venv.close()
    eval_env.close()
    return out / "model.zip"


def _record_run(out: Path, run: dict[str, Any]) -> None:
    """``out/run.json``: this run's record; a resumed run's joins the earlier ones under
    ``resumes`` (the first run's command and settings stay on top)."""
    path = out / RUN_FILE
    if run["resumed_from_steps"] is not None and path.is_file():
        first = json.loads(path.read_text())
        run = {**first, "resumes": [*first.get("resumes", []), run]}
    atomic_write_text(path, json.dumps(run, indent=2))


def _resumed(
    spec: AgentSpec, venv: VecEnv, start: tuple[Path, int], tensorboard: str | Path | None
) -> tuple[VecEnv, BaseAlgorithm]:
    """The envs (with the checkpoint's normaliser statistics) and the agent of checkpoint
    ``start`` (with its replay buffer, for an off-policy agent)."""
    path, steps = start
    stats = path.parent / f"agent_vecnormalize_{steps}_steps.pkl"
    if isinstance(venv, VecNormalize):
        if not stats.is_file():
            raise FileNotFoundError(f"resume: checkpoint {os.fspath(path)!r} has no normaliser statistics")
        venv = VecNormalize.load(str(stats), venv.venv)
    log = None if tensorboard is None else str(tensorboard)
    agent = ALGOS[spec.algo].load(path, env=venv, device="cpu", tensorboard_log=log)
    buffer = path.parent / f"agent_replay_buffer_{steps}_steps.pkl"
    if hasattr(agent, "load_replay_buffer"):
        if not buffer.is_file():
            raise FileNotFoundError(f"resume: checkpoint {os.fspath(path)!r} has no replay buffer beside it")
        agent.load_replay_buffer(buffer)
    return venv, agent


def _keep_curve(evaluate: EvalCallback, out: Path, steps: int) -> None:
    """Seed ``evaluate``'s learning curve with the evaluations of ``out`` up to ``steps``."""
    path = out / "evaluations.npz"
    if not path.exists():
        return
    with np.load(path) as data:
        keep = data["timesteps"] <= steps
        if data["results"].shape[1] != evaluate.n_eval_episodes:
            had = data["results"].shape[1]
            raise ValueError(f"resume: the learning curve has {had} episodes per evaluation, "
                             f"this run {evaluate.n_eval_episodes}: resume with as many")  # fmt: skip
        evaluate.evaluations_timesteps = data["timesteps"][keep].tolist()
        evaluate.evaluations_results = data["results"][keep].tolist()
        evaluate.evaluations_length = data["ep_lengths"][keep].tolist()


def _plot_learning_curve(out: Path) -> None:
    from estimator_service.plots import save_figure

    data = np.load(out / "evaluations.npz") if (out / "evaluations.npz").exists() else None
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    if data is not None and len(data["timesteps"]):
        r = data["results"]
        ax.plot(data["timesteps"], r.mean(axis=1), marker="o")
        ax.fill_between(data["timesteps"], r.min(axis=1), r.max(axis=1), alpha=0.2)
    ax.set(xlabel="environment steps", ylabel="evaluation return", title="learning curve")
    fig.tight_layout()
    save_figure(fig, out / "learning_curve.png")


def _relative_models(spec: AgentSpec, folder: Path) -> AgentSpec:
    """``spec`` with its model folder written relative to the agent's folder ``folder``."""
    if spec.models is None:
        return spec
    return replace(spec, models=os.path.relpath(Path(spec.models).resolve(), folder.resolve()))


def agent_folder(path: str | Path) -> Path:
    """The folder of a saved agent (its ``agent.json``) named by its folder or by one of its
    model files: ``model.zip``, another ``.zip`` beside it, or a checkpoint in its
    ``checkpoints/``."""
    path = Path(path)
    if path.suffix != ".zip":
        return path
    beside = path.parent
    if not (beside / "agent.json").is_file() and beside.name == CHECKPOINTS:
        return beside.parent
    return beside


def load_agent(path: str | Path, models: str | Path | None = None) -> tuple[BaseAlgorithm, AgentSpec]:
    """A saved agent and its :class:`AgentSpec`: ``path`` a folder (its ``model.zip``) or the
    model file itself (e.g. a checkpoint), with ``agent.json`` in the agent's folder
    (:func:`agent_folder`).

    The spec's model folder is resolved against the agent's folder (so an agent and its
    models can move together and be run from any directory); ``models`` overrides it.
    """
    if Path(path).is_file() and Path(path).suffix != ".zip":
        raise ValueError(f"agent {os.fspath(path)!r}: a file, not an agent's folder or its .zip model")
    folder = agent_folder(path)
    model_file = Path(path) if Path(path).suffix == ".zip" else folder / "model.zip"
    spec_file = folder / "agent.json"
    for f in (spec_file, model_file):
        if not f.is_file():
            raise FileNotFoundError(f"agent {os.fspath(path)!r}: no {f.name} in {os.fspath(f.parent)!r}")
    spec = AgentSpec(**json.loads(spec_file.read_text()))
    if models is not None:
        spec = replace(spec, models=str(Path(models)))
    elif spec.models is not None and not Path(spec.models).is_absolute():
        spec = replace(spec, models=os.path.normpath(folder.absolute() / spec.models))
    return ALGOS[spec.algo].load(model_file, device="cpu"), spec


def observation_normalizer(path: str | Path) -> Callable[[Any], Any]:
    """What a saved agent's policy sees of an observation: SB3's ``VecNormalize`` of its
    training (``vecnormalize.pkl`` beside ``model.zip``) frozen, or the observation itself
    for an agent trained without ``normalize``."""
    file = agent_folder(path) / NORMALIZER_FILE
    if not file.is_file():
        return lambda obs: obs
    import pickle

    with file.open("rb") as f:
        norm = pickle.load(f)  # SB3's own format; the agent's model.zip is trusted alike
    if not isinstance(norm, VecNormalize):
        raise ValueError(f"{os.fspath(file)!r} does not hold SB3's VecNormalize statistics")
    norm.training = False
    return norm.normalize_obs


def evaluate_agent(
    path: str | Path, episodes: int = 5, seed: int = 1000, on_episode: Callable[[int], None] | None = None,
    models: str | Path | None = None,
) -> dict[str, float]:  # fmt: skip
    """Mean return, task success (:func:`~agents.rl.registry.episode_success`) and, for
    belief agents, the RMS position error of the belief, over ``episodes`` episodes seeded
    ``seed``, ``seed + 1``, ... (``models`` overrides the agent's model folder)."""
    agent, spec = load_agent(path, models)
    env = make_env(AgentSpec(**{**asdict(spec), "seed": seed}))
    norm = observation_normalizer(path)

    def act(obs: Any, info: dict[str, Any]) -> Any:
        return agent.predict(norm(obs), deterministic=True)[0]

    return _evaluate(env, act, episodes, seed, on_episode)


def evaluate_pilot(task: str, episodes: int = 5, seed: int = 1000) -> dict[str, float]:
    """:func:`evaluate_agent`'s figures for the hand-written :class:`~agents.pilots.WaypointPilot`
    flying on the true state towards the goal, on the same episodes."""
    import gymnasium as gym

    from agents.pilots import WaypointPilot

    pilot = WaypointPilot()
    env = gym.make(TASK_ENVS[task])

    def act(obs: Any, info: dict[str, Any]) -> Any:
        return pilot.act(info["state"], info["goal"])

    return _evaluate(env, act, episodes, seed, None)


def _evaluate(
    env: Any, act: Callable[[Any, dict[str, Any]], Any], episodes: int, seed: int,
    on_episode: Callable[[int], None] | None,
) -> dict[str, float]:  # fmt: skip
    returns, success, err2, n = [], [], 0.0, 0
    for ep in range(episodes):
        obs, info = env.reset(seed=seed + ep)
        done, total = False, 0.0
        while not done:
            obs, r, terminated, truncated, info = env.step(act(obs, info))
            total += float(r)
            done = terminated or truncated
            if "belief_mean" in info:
                err2 += float(np.sum((info["belief_mean"][:3] - info["state"][:3]) ** 2))
                n += 1
        returns.append(total)
        success.append(episode_success(info))
        if on_episode:
            on_episode(ep + 1)
    env.close()
    return {
        "mean_return": float(np.mean(returns)),
        "std_return": float(np.std(returns)),
        "success_rate": float(np.mean(success)),
        "belief_position_rms_mm": float(1000 * math.sqrt(err2 / n)) if n else math.nan,
    }


class AgentPolicy:
    """A saved agent as a recorder policy ``policy(obs, info) -> action``.

    It keeps its own estimate exactly as the agent's training wrapper did: reset at the
    mocap state when ``info["t"] == 0``, then one filter step per call with the previous
    action and the new raw observation.
    """

    def __init__(self, path: str | Path) -> None:
        import gymnasium as gym

        from agents.rl.wrappers import BeliefObservation

        self.agent, spec = load_agent(path)
        self.normalize = observation_normalizer(path)
        self.shadow = BeliefObservation(
            gym.make(TASK_ENVS[spec.task]),
            spec.variant,
            models=spec.models,
            filter=spec.filter,
            model=spec.model,
            seed=spec.seed,
        )
        self._prev: np.ndarray | None = None

    def __call__(self, obs: dict[str, Any], info: dict[str, Any]) -> np.ndarray:
        if self._prev is None or float(info["t"]) == 0.0:
            self.shadow.reset_belief(info)
            self.shadow.last_action = np.zeros(3)
        else:
            self.shadow.advance_belief(self._prev, obs, info)
            self.shadow.last_action = self._prev
        action, _ = self.agent.predict(self.normalize(self.shadow.features(obs, info)), deterministic=True)
        self._prev = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        return self._prev
