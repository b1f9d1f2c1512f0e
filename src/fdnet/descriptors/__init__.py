"""One interface for every method: a batch of images -> one vector per image.

FDNet and every baseline implement :class:`~fdnet.descriptors.base.Descriptor`, so matching,
evaluation and experiments never special-case a method. ``create(name, ...)`` builds one by the
name used on the command line (``--method``).
"""

from fdnet.descriptors.base import Descriptor, describe_paths, l2_normalize
from fdnet.descriptors.registry import available_methods, create

__all__ = ["Descriptor", "describe_paths", "l2_normalize", "available_methods", "create"]
