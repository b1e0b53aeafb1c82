"""fastneus.baselines: reference implementations for comparisons.

- :mod:`fastneus.baselines.neus_mlp`: paper-faithful ActiveNeuS (NeuS MLPs + sampler) in plain torch.
"""
from fastneus.baselines.neus_mlp import BaselineConfig, BaselineField, BaselineTrainer, baseline_config

__all__ = ["BaselineConfig", "BaselineField", "BaselineTrainer", "baseline_config"]
