"""A DreamerV3-style latent world model (RSSM) trained on stores, and the scorer that ranks proposals in imagination."""
