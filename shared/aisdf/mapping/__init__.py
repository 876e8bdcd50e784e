"""iSDF's continual SDF learning with AiSDF's Atlanta-aware sampling and loss (pure algorithm)."""

from .config import TrainingConfig
from .frames import Frame, KeyframeStore
from .presets import PRESETS, training_config
from .trainer import Trainer

__all__ = ["Frame", "KeyframeStore", "PRESETS", "Trainer", "TrainingConfig", "training_config"]
