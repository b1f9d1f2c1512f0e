"""Training, the side path that produces run directories: the one loop every trained method runs
on (:mod:`fdnet.training.loop`), training data (:mod:`fdnet.training.data`), several processes
(:mod:`fdnet.training.distributed`) and the CSV/TensorBoard log. Each method's own step lives in
``fdnet.methods.<name>.training``, with what only that method uses (FDNet's losses and
domain-balanced sampler are :mod:`fdnet.methods.fdnet.losses` and :mod:`fdnet.methods.fdnet.sampler`).

Inference (descriptors, ``fdnet.load``, export) never imports this package.
"""
