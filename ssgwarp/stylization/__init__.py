"""Key views, Stage 1 (diffusion + CVSA), Stage 2 (ssgwarp keyviews, ssgwarp stylize).

Modules: cvsa, diffusion, diffusion_models, keyviews, matching, stage2, stylize."""
