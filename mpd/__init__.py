"""mpd: Motion Planning Diffusion (Carvalho et al., IEEE T-RO 2025), reproducible."""

__version__ = "0.1.0"
