"""The ``ssgwarp`` commands, one module each: ``add_arguments(parser)`` (the options) and ``run(args) -> int``
(build the library's config from the options, call the library function, print the result). The commands sit at
the top of the package: they may import every layer, and no layer imports them (``ssgwarp.cli`` wires them up).

Modules: demo, reconstruct, import_ (``ssgwarp import``), masks, group, keyviews, stylize, evaluate, view, render,
export, weights."""
