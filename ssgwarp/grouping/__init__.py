"""Instance masks and Gaussian Grouping: the stage (``ssgwarp group``, :mod:`.stage`), its model and
losses (:mod:`.model`), mask files (:mod:`.mask_files`), training (:mod:`.train`), cross-view agreement
(:mod:`.agreement`), Segment Anything masks (``ssgwarp masks``, :mod:`.segment`), their association
across views (:mod:`.association`) and the mask-free pseudo-masks (:mod:`.pseudomasks`).
"""
