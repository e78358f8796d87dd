"""Plain networks and the two diffusion processes (DDPM/DDIM for the policy, EDM for the visual world model)."""
