"""Gymnasium retraction environments (``heml_gym.envs``), built on the HEML backend."""
