"""Key views, Stage 1 (diffusion + CVSA), Stage 2 (ssgwarp keyviews, ssgwarp stylize).

Modules: batches, color (Stage 2's colour transfer), cvsa, densify, diffusion, diffusion_models, feature_defaults,
keyviews, matching, regions, spread, stage2, stylize, targets."""
