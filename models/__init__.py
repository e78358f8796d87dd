"""Networks, the components that learn (policy, world models, rewards), the planners, and how they train.

One folder per concept (DIAMOND's split, one training contract):

- ``networks``: plain networks and diffusion processes: the FiLM 1-D U-Net, the AdaGroupNorm 2-D U-Net,
  ResNet18 with spatial softmax, the MLP, the observation encoders, DDPM/DDIM (``ddpm``) and EDM (``edm``);
- ``policy``: Diffusion Policy: its config and profiles, the denoiser, the LightningModule, the BC controller;
- ``world_models``: the state MLP and visual EDM dynamics, the module that trains either, open-loop evaluations;
- ``rewards``: the registration reward, the learned image reward, the VLM selector;
- ``planning``: the protocols planners depend on, the objective, the planners (a class per search, registered by
  name), configs and ``load_planner``;
- ``values``, ``latent``, ``ladi``: the paper's baselines' models: V-GPS's IQL Q-function, a DreamerV3-style RSSM,
  a LaDi-WM-style latent diffusion model (``docs/baselines.md``);
- ``training``: ``TrainableModule`` (the contract every component follows) and ``train``, run configs and
  profiles, checkpoints, EMA, the optimiser recipe.

``gpc.models`` imports ``gpc.datasets`` only; a task reaches it as a ``gpc.datasets.layout.TaskLayout``.
Submodules are imported explicitly so that importing one piece does not pull in Lightning.
"""
