"""Diffusion Policy: config and profiles, denoiser, LightningModule, and the behaviour-cloning controller."""
