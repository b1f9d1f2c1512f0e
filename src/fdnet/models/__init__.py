"""FDNet networks: encoders, decoder, pairwise discriminator (paper section 4.1)."""

from fdnet.models.decoder import Decoder
from fdnet.models.discriminator import PairDiscriminator
from fdnet.models.encoder import Encoder
from fdnet.models.fdnet import FDNet, FDNetConfig, validate_architecture

__all__ = ["Encoder", "Decoder", "PairDiscriminator", "FDNet", "FDNetConfig", "validate_architecture"]
