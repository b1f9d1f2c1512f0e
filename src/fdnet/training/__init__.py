"""Training, the side path that produces run directories: the one loop every trained method runs
on (:mod:`fdnet.training.loop`), training data (:mod:`fdnet.training.data`), composable losses,
the domain-balanced sampler and the CSV/TensorBoard log. Each method's own step lives in
``fdnet.methods.<name>.training``.

Inference (descriptors, ``fdnet.load``, export) never imports this package.
"""
