"""A LaDi-WM-style world model: diffusion over the future latents of the policy's frozen encoder, a reward on them."""
