"""LightningModules for the policy, world models and reward predictors (see the later issues)."""
