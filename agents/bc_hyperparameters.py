"""Behaviour cloning's hyperparameters (``algorithm.hyperparameters`` of a BC run config),
apart from the training code (:mod:`heml_gym.agents.bc`) so that validating a config
needs neither torch nor the training modules."""

from __future__ import annotations

import numpy as np

__all__ = ["BehaviourCloning"]


class BehaviourCloning:
    """BC's hyperparameters (``algorithm.hyperparameters`` of a run config).

    hidden : sequence of int
        Widths of the MLP's hidden ReLU layers.
    epochs : int
        Passes over the demonstrations.
    batch_size : int
        Transitions per Adam step.
    learning_rate : float
        Adam's step size.
    weight_decay : float
        Adam's L2 penalty on the weights.
    """

    def __init__(self, hidden=(256, 256), epochs: int = 200, batch_size: int = 256, learning_rate: float = 1e-3,
                 weight_decay: float = 0.0):
        hidden = list(hidden) if isinstance(hidden, (list, tuple)) else hidden
        if not isinstance(hidden, list) or not hidden or not all(
                isinstance(h, int) and not isinstance(h, bool) and h >= 1 for h in hidden):
            raise ValueError(f"hidden: a list of layer widths >= 1, got {hidden!r}")
        for name, value in (("epochs", epochs), ("batch_size", batch_size)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name}: an integer >= 1, got {value!r}")
        for name, value, low in (("learning_rate", learning_rate, 0.0), ("weight_decay", weight_decay, None)):
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value) and (
                value > low if low is not None else value >= 0)
            if not ok:
                hint = ""
                try:
                    float(value) if isinstance(value, str) else None
                    hint = " (YAML reads 1e-3 as text: write 1.0e-3 or 0.001)" if isinstance(value, str) else ""
                except ValueError:
                    pass
                raise ValueError(f"{name}: a finite number {'> 0' if low is not None else '>= 0'}, got {value!r}{hint}")
        self.hidden, self.epochs, self.batch_size = hidden, epochs, batch_size
        self.learning_rate, self.weight_decay = float(learning_rate), float(weight_decay)
