"""3DGS reconstruction (ssgwarp reconstruct): the trainer, its recipe, densification.

Modules: recipe, reconstruct, strategy, trainer."""
