"""Stable-Baselines3 training, evaluation and rerun rollouts (``heml_gym.agents``)."""
