"""Shared services: run folders, the checkpointed loop, losses, weights, DDP, networks, colour.

Modules: color, distributed, features, loop, losses, networks, runs, weight_specs, weights."""
