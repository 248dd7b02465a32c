"""Shared plumbing that several layers use: run folders, the checkpointed loop, losses, weights, DDP.

Modules: distributed, loop, losses, runs, weight_specs, weights, weights_command (the table behind ``ssgwarp weights``)."""
