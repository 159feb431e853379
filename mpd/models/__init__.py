"""Generative priors over trajectory control points: temporal U-Net, context encoders, Gaussian diffusion
(schedule, DDPM/DDIM steps, samplers), the CVAE baseline, training and checkpoints."""

from mpd.models.checkpoint import LoadedModel, build_network, load_model, read_checkpoint
from mpd.models.context import EE_GOAL, JOINT_GOAL, ContextEncoder, context_keys
from mpd.models.cvae import CVAE, kl_standard_normal
from mpd.models.data import SPLIT_TEST, SPLIT_TRAIN, SPLIT_VAL, TrainingArrays, fit_normalizers
from mpd.models.diffusion import (
    DiffusionModel,
    Schedule,
    ddim_step,
    ddim_timesteps,
    ddpm_step,
    get_schedule,
    predict_x0,
    q_sample,
    sample,
)
from mpd.models.normalizer import Normalizer
from mpd.models.train import list_models, model_dir, model_identity, train_model
from mpd.models.unet import TemporalUnet

__all__ = [
    "CVAE",
    "EE_GOAL",
    "JOINT_GOAL",
    "SPLIT_TEST",
    "SPLIT_TRAIN",
    "SPLIT_VAL",
    "ContextEncoder",
    "DiffusionModel",
    "LoadedModel",
    "Normalizer",
    "Schedule",
    "TemporalUnet",
    "TrainingArrays",
    "build_network",
    "context_keys",
    "ddim_step",
    "ddim_timesteps",
    "ddpm_step",
    "fit_normalizers",
    "get_schedule",
    "kl_standard_normal",
    "list_models",
    "load_model",
    "model_dir",
    "model_identity",
    "predict_x0",
    "q_sample",
    "read_checkpoint",
    "sample",
    "train_model",
]
