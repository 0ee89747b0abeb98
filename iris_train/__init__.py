"""IRIS in torch: model stages, geometry, data, training and evaluation."""
from .config import PRESETS, ModelConfig, preset
from .model import CheckpointError, IrisModel, Scene, build_model, load_model, read_checkpoint, save_checkpoint

__all__ = ["ModelConfig", "PRESETS", "preset", "IrisModel", "Scene", "build_model", "load_model",
           "read_checkpoint", "save_checkpoint", "CheckpointError"]
