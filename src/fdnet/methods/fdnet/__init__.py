"""FDNet (the paper's method): ``config`` (presets), ``model`` (encoders, decoder, pairwise
discriminator, optional frozen trunk), ``descriptor`` (content vectors of a run) and
``training`` (the staged adversarial step on the shared loop)."""
