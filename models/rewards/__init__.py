"""Rewards that score predicted futures: registration (state), learned (image), and a VLM that selects."""
