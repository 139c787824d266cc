"""Training: value networks of any activation layout learned from the HJI residual.

``ValueNetwork(system, layout="ssrsl")`` builds a network; ``Trainer(config, run_dir).train()`` runs
a resumable training run; ``load_network(checkpoint)`` and ``load_deepreach(path, system, layout)``
load ours and DeepReach's; ``NeuralValueFunction`` puts a network behind the value-function interface.
"""

from training.checkpoint import load_network, save_checkpoint
from training.config import TrainConfig, parse_duration
from training.deepreach import load_deepreach
from training.encoding import Encoding
from training.layers import ACTIVATIONS, parse_layout
from training.network import NeuralValueFunction, ValueNetwork
from training.trainer import Trainer, TrainingDivergedError, TrainingInterrupted

__all__ = [
    "ACTIVATIONS",
    "Encoding",
    "NeuralValueFunction",
    "TrainConfig",
    "Trainer",
    "TrainingDivergedError",
    "TrainingInterrupted",
    "ValueNetwork",
    "load_deepreach",
    "load_network",
    "parse_duration",
    "parse_layout",
    "save_checkpoint",
]
