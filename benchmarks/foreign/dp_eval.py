"""Evaluate a Diffusion Policy low-dim Push-T checkpoint in DP's OWN Push-T keypoints environment.

Run from OUTSIDE the repository:
  cd /tmp && OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 nice -n 5 /work/refenv/bin/python benchmarks/foreign/dp_eval.py \
      [--ckpt PATH] [--mode batched|perseed] [--n 100] [--out JSON]

Loading = DP's eval.py: torch.load(pickle_module=dill) -> hydra.utils.get_class(cfg._target_)(cfg) -> load_payload
-> ema_model if cfg.training.use_ema.
Episodes = DP's PushTKeypointsRunner.run() conventions (env_runner/pusht_keypoints_runner.py), with its SyncVectorEnv
semantics re-done as a Python list of envs: each env is DP's MultiStepWrapper(PushTKeypointsEnv(legacy=legacy_test,
keypoint_visible_rate, agent_keypoints=False, **genenerate_keypoint_manager_params()), n_obs_steps, n_action_steps,
max_episode_steps=max_steps); per env `env.seed(seed)` then `env.reset()`; loop until all done:
Do = obs.shape[-1] // 2; obs_dict = {'obs': obs[..., :n_obs_steps, :Do].float32, 'obs_mask': ...};
policy.predict_action(obs_dict)['action'][:, n_latency_steps:] -> env.step(action) (8 steps, the wrapper stops an
env once it is done or has taken max_steps); score = max over the wrapper's per-step reward list.
(DP's VideoRecordingWrapper is left out: with file_path None it is a pass-through, and it needs PyAV.)
"""
import argparse
import json
import os
import sys
import time
import types
import typing
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

sys.path[:] = [p for p in sys.path if not str(Path(p or os.getcwd()).resolve()).startswith(str(REPO))]

import numpy as np  # noqa: E402
import torch  # noqa: E402

DP_SRC = Path(os.environ.get("DP_SRC", "/tmp/dp_src"))
CKPT = Path(REPO / "runs/dp/train_lowdim/checkpoints/latest.ckpt")


def setup_dp():
    sys.path.insert(0, str(DP_SRC))
    import diffusers  # noqa: F401
    import diffusers.optimization as dopt
    import diffusers.schedulers.scheduling_ddpm  # noqa: F401
    import diffusers.training_utils  # noqa: F401
    sys.modules.setdefault("wandb", types.ModuleType("wandb"))
    for n, v in (("Union", typing.Union), ("Optional", typing.Optional), ("Optimizer", torch.optim.Optimizer)):
        if not hasattr(dopt, n):
            setattr(dopt, n, v)
    # matplotlib >= 3.9 removed cm.get_cmap; DP's PymunkKeypointManager uses it only to pick keypoint DRAW colours.
    import matplotlib
    import matplotlib.cm
    if not hasattr(matplotlib.cm, "get_cmap"):
        matplotlib.cm.get_cmap = matplotlib.colormaps.get_cmap
    from omegaconf import OmegaConf
    OmegaConf.register_new_resolver("eval", eval, replace=True)


def load_like_eval(ckpt):
    import dill
    import hydra
    # DP's eval.py: torch.load(open(checkpoint, 'rb'), pickle_module=dill); torch>=2.6 needs weights_only=False
    payload = torch.load(open(ckpt, "rb"), pickle_module=dill, weights_only=False)
    cfg = payload["cfg"]
    cls = hydra.utils.get_class(cfg._target_)
    workspace = cls(cfg, output_dir="/tmp/dp_eval_out")
    workspace.load_payload(payload, exclude_keys=None, include_keys=None)
    policy = workspace.model
    if cfg.training.use_ema:
        policy = workspace.ema_model
    policy.to(torch.device("cpu"))
    policy.eval()
    return cfg, policy, workspace


def make_env_fn(rcfg):
    from diffusion_policy.env.pusht.pusht_keypoints_env import PushTKeypointsEnv
    from diffusion_policy.gym_util.multistep_wrapper import MultiStepWrapper
    kp_kwargs = PushTKeypointsEnv.genenerate_keypoint_manager_params()

    def env_fn():
        return MultiStepWrapper(
            PushTKeypointsEnv(legacy=rcfg.legacy_test, keypoint_visible_rate=rcfg.keypoint_visible_rate,
                              agent_keypoints=rcfg.agent_keypoints, **kp_kwargs),
            n_obs_steps=rcfg.n_obs_steps + rcfg.n_latency_steps,
            n_action_steps=rcfg.n_action_steps,
            max_episode_steps=rcfg.max_steps)
    return env_fn


def run_chunk(envs, seeds, policy, rcfg, torch_seed):
    """One chunk of PushTKeypointsRunner.run() over len(envs) envs (SyncVectorEnv semantics)."""
    assert not rcfg.past_action and not rcfg.agent_keypoints
    for env, seed in zip(envs, seeds):
        env.seed(seed)  # the runner's init_fn: env.seed(seed)
    if torch_seed is not None:
        torch.manual_seed(torch_seed)
    obs = np.stack([env.reset() for env in envs])  # (B, To, 40) float64
    policy.reset()
    done = False
    n_calls = 0
    while not done:
        Do = obs.shape[-1] // 2
        np_obs_dict = {"obs": obs[..., :rcfg.n_obs_steps, :Do].astype(np.float32),
                       "obs_mask": obs[..., :rcfg.n_obs_steps, Do:] > 0.5}
        obs_dict = {k: torch.from_numpy(v) for k, v in np_obs_dict.items()}
        with torch.no_grad():
            action_dict = policy.predict_action(obs_dict)
        action = action_dict["action"].detach().cpu().numpy()[:, rcfg.n_latency_steps:]
        res = [env.step(a) for env, a in zip(envs, action)]
        obs = np.stack([r[0] for r in res])
        done = bool(np.all([r[2] for r in res]))
        n_calls += 1
    rewards = [list(env.get_attr("reward")) for env in envs]
    return [float(np.max(r)) for r in rewards], [len(r) for r in rewards], n_calls


def initial_states(env_fn, seeds):
    from diffusion_policy.env.pusht.pusht_env import PushTEnv
    out = []
    for s in seeds:
        env = env_fn()
        env.seed(s)
        obs = env.reset()
        e = env.env
        rs = np.random.RandomState(seed=s)  # the draws PushTEnv.reset makes (legacy RandomState)
        sampled = [rs.randint(50, 450), rs.randint(50, 450), rs.randint(100, 400), rs.randint(100, 400),
                   rs.randn() * 2 * np.pi - np.pi]
        out.append({
            "seed": s,
            "sampled_state": [float(x) for x in sampled],
            "agent_pos": [float(x) for x in e.agent.position],
            "block_pos": [float(x) for x in e.block.position],
            "block_angle_rad": float(e.block.angle),
            "state_obs_PushTEnv": [float(x) for x in PushTEnv._get_obs(e)],
            "obs20": [float(x) for x in obs[-1, :20]],
        })
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ckpt", default=str(CKPT))
    ap.add_argument("--mode", choices=["batched", "perseed"], default="batched")
    ap.add_argument("--torch-seed", type=int, default=0, help="batched mode: torch.manual_seed before the chunk")
    ap.add_argument("--notes", default="")
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--start", type=int, default=None)
    ap.add_argument("--out", default=str(REPO / "runs/dp/eval_dp_own.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    setup_dp()
    cfg, policy, ws = load_like_eval(args.ckpt)
    rcfg = cfg.task.env_runner
    start = rcfg.test_start_seed if args.start is None else args.start
    seeds = list(range(start, start + args.n))
    env_fn = make_env_fn(rcfg)
    t0 = time.time()
    if args.mode == "batched":
        # the runner: n_envs = n_train + n_test -> one chunk with all test seeds; global torch RNG, seeded once
        envs = [env_fn() for _ in seeds]
        scores, lens, calls = run_chunk(envs, seeds, policy, rcfg, torch_seed=args.torch_seed)
        torch_seeding = (f"torch.manual_seed({args.torch_seed}) once (after env.seed, before env.reset), "
                         "then all seeds batched (B=len(seeds)) like the runner's single chunk")
    else:
        scores, lens = [], []
        for s in seeds:
            sc, ln, _ = run_chunk([env_fn()], [s], policy, rcfg, torch_seed=s)
            scores += sc
            lens += ln
            print(json.dumps({"seed": s, "score": sc[0], "env_steps": ln[0], "elapsed_s": round(time.time() - t0, 1)}),
                  flush=True)
        torch_seeding = "per seed: torch.manual_seed(seed) right before env.reset(); one env, B=1 per predict_action"
    wall = time.time() - t0
    x = np.asarray(scores)
    n = len(x)
    m = float(x.mean())
    from scipy import stats
    half = float(stats.t.ppf(0.975, n - 1) * x.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
    rng = np.random.default_rng(0)
    boots = x[rng.integers(0, n, (10000, n))].mean(1)
    succ = x >= 1.0
    k = int(succ.sum())
    z = 1.959963984540054
    p = k / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    pol = cfg.policy
    result = {
        "checkpoint": str(Path(args.ckpt).resolve()),
        "global_step": int(ws.global_step), "epoch": int(ws.epoch),
        "seeds": seeds, "scores": scores, "env_steps": lens,
        "mean": m,
        "ci95": {"t": [m - half, m + half], "bootstrap_percentile_10000_seed0":
                 [float(np.percentile(boots, 2.5)), float(np.percentile(boots, 97.5))]},
        "success_rate": k / n, "n_success": k,
        "success_ci95_wilson": [float(c - h), float(c + h)],
        "mode": args.mode, "torch_seeding": torch_seeding, "eval_wall_s": round(wall, 1),
        "runner_conventions": {
            "env": "diffusion_policy.env.pusht.pusht_keypoints_env.PushTKeypointsEnv wrapped in "
                   "diffusion_policy.gym_util.multistep_wrapper.MultiStepWrapper (reward_agg max)",
            "legacy": bool(rcfg.legacy_test), "keypoint_visible_rate": float(rcfg.keypoint_visible_rate),
            "render_size": 96, "agent_keypoints": bool(rcfg.agent_keypoints), "past_action": bool(rcfg.past_action),
            "n_obs_steps": int(rcfg.n_obs_steps), "n_action_steps": int(rcfg.n_action_steps),
            "n_latency_steps": int(rcfg.n_latency_steps), "max_steps": int(rcfg.max_steps),
            "test_start_seed": int(rcfg.test_start_seed),
            "obs_fed": "obs[..., :n_obs_steps, :Do] with Do = 40 // 2 = 20 (9 block keypoints xy + agent xy), float32",
            "action_executed": "predict_action(...)['action'] = action_pred[:, n_obs_steps-1 : n_obs_steps-1+8], "
                               "stepped one by one by MultiStepWrapper",
            "reset_obs_history": "MultiStepWrapper pads the history by repeating the reset obs",
            "score": "max over the per-step rewards (DP runner max_rewards); reward = clip(coverage/0.95, 0, 1)",
            "sampler": f"DDPM {int(pol.noise_scheduler.num_train_timesteps)} train steps, num_inference_steps "
                       f"{int(pol.num_inference_steps)}, {pol.noise_scheduler.beta_schedule}, "
                       f"{pol.noise_scheduler.variance_type}, clip_sample {pol.noise_scheduler.clip_sample}",
        },
        "initial_states_100000_100004": initial_states(env_fn, list(range(100000, 100005))),
        "notes": args.notes,
    }
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: result[k] for k in ("mean", "ci95", "success_rate", "success_ci95_wilson", "eval_wall_s")}),
          flush=True)


if __name__ == "__main__":
    main()
