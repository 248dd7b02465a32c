"""Instance masks and Gaussian Grouping: the stage (``ssgwarp group``, :mod:`.stage`), its model and
losses (:mod:`.model`), mask files (:mod:`.mask_files`), training (:mod:`.train`), cross-view agreement
(:mod:`.agreement`), Segment Anything masks (``ssgwarp masks``, :mod:`.segment`), their association
across views (:mod:`.association`) and the mask-free pseudo-masks (:mod:`.pseudomasks`).

The stage's public names are reached here too (``from ssgwarp.grouping import group_scene``, as before
the package was split into layers); the stage is imported on the first such use, so importing one
part (``ssgwarp.grouping.model``) does not load the whole stage.
"""
from importlib import import_module

_STAGE = frozenset({
    "DEFAULT_DIM", "FORMAT", "GroupConfig", "GroupModel", "GroupingHook", "KINDS", "MaskSet", "RunInfo",
    "add_arguments", "find_mask", "gaussian_groups", "group_labels", "group_scene", "init_identities",
    "knn_indices", "load_groups", "load_masks", "make_classifier", "map_name", "mask_loss",
    "neighbour_pairs", "read_id_image", "regularizer_3d", "render_group_maps", "reprojection_agreement",
    "run", "train_identities", "write_group_outputs",
})


def __getattr__(name: str):
    if name in _STAGE:
        return getattr(import_module(".stage", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_STAGE))
