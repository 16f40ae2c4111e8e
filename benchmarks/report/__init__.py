"""Report studies (see :mod:`heml_gym.benchmarks`)."""
