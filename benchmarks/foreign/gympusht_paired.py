"""LeRobot's policy, pre/post processors and gym-pusht, started from gpc's (Diffusion Policy's) initial states.

gym-pusht >= 0.1.6 draws a seed's initial state from gymnasium's generator, gpc (like Diffusion
Policy) from RandomState; reset_to_state puts both environments in the same start, so the BC scores
pair by seed. Run with /work/refenv/bin/python from /tmp: PATH OUT [first last].
"""
import json
import sys
import time

import gym_pusht  # noqa: F401
import gymnasium as gym
import numpy as np
import torch
from lerobot.envs.utils import preprocess_observation
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.factory import make_pre_post_processors

torch.set_num_threads(1)
path, out = sys.argv[1], sys.argv[2]
first, last = (int(sys.argv[3]), int(sys.argv[4])) if len(sys.argv) > 4 else (100000, 100100)
policy = DiffusionPolicy.from_pretrained(path)
policy.eval()
pre, post = make_pre_post_processors(policy.config, pretrained_path=path)


def dp_state(seed):
    rs = np.random.RandomState(seed=seed)
    return np.array([rs.randint(50, 450), rs.randint(50, 450), rs.randint(100, 400), rs.randint(100, 400),
                     rs.randn() * 2 * np.pi - np.pi], dtype=np.float64)


env = gym.make("gym_pusht/PushT-v0", obs_type="environment_state_agent_pos", max_episode_steps=300)
rows, t0 = [], time.time()
for seed in range(first, last):
    torch.manual_seed(seed)
    obs, _ = env.reset(seed=seed, options={"reset_to_state": dp_state(seed)})
    start = np.concatenate([obs["agent_pos"], env.unwrapped.block.position, [env.unwrapped.block.angle]]).tolist()
    policy.reset()
    best, steps, success = 0.0, 0, False
    for _ in range(300):
        batch = pre(preprocess_observation({k: np.asarray(v)[None] for k, v in obs.items()}))
        with torch.no_grad():
            action = post(policy.select_action(batch))
        obs, reward, terminated, truncated, info = env.step(action[0].numpy())
        best, steps = max(best, float(reward)), steps + 1
        if terminated:
            success = True
            break
        if truncated:
            break
    rows.append({"seed": seed, "score": best, "success": success, "steps": steps, "start": start})
scores = np.array([r["score"] for r in rows])
json.dump({"episodes": rows, "mean_score": float(scores.mean()), "success_rate": float(np.mean([r["success"] for r in rows])),
           "wall_s": time.time() - t0}, open(out, "w"), indent=1)
print(f"{len(rows)} episodes: mean {scores.mean():.3f}, success {np.mean([r['success'] for r in rows]):.2f}")
