"""FDNet training: losses, the domain-balanced sampler, configs/presets, run directories
(checkpoints) and the staged adversarial trainer.

Submodules are imported on use (``from fdnet.training.checkpoint import save_run``) so that
importing one piece does not pull in the others.
"""
