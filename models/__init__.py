"""Networks and LightningModules (policy now; world models and reward predictors follow).

Split as DIAMOND splits its diffusion stack:

- plain networks: ``unet1d`` (Diffusion Policy's FiLM 1-D U-Net), ``resnet`` (ResNet18 with
  GroupNorm, spatial softmax), ``encoders`` (one observation-encoder interface for state,
  keypoint and image observations);
- diffusion: ``diffusion`` (DDPM schedule, DDPM/DDIM samplers), ``ema`` (EMA weights);
- the policy: ``policy_config`` (frozen configs and profiles), ``denoiser`` (network + DDPM
  loss), ``policy`` (``PolicyModule``: batch in, loss and logs out; ``sample`` /
  ``sample_batch`` out), ``checkpoint`` (kind/task records, clear load errors),
  ``training`` (``train_policy``: one run with best/last checkpoints and resume);
- world models: ``world_model_config`` (state and visual configs, profiles), ``world_model``
  (``StateDynamics`` MLP and ``WorldModelModule``, which trains and checkpoints either kind),
  ``visual_world_model`` (``VisualDynamics``: frames in, frames out), ``edm`` (EDM
  preconditioned ``Denoiser`` and ``EulerSampler``, frozen or sampled noise), ``unet2d``
  (AdaGroupNorm U-Net), ``world_model_training``, ``world_model_eval`` /
  ``visual_world_model_eval`` (per-step errors against the nothing-moves baseline);
- ``protocols``: the interfaces planners use.

Submodules are imported explicitly (``from models.policy import PolicyModule``) so that
importing one piece does not pull in Lightning. ``models`` imports ``datasets`` only.
"""
