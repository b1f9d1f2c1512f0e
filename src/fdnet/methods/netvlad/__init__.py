"""NetVLAD (Arandjelovic et al., CVPR 2016) on the pretrained EfficientNet-Lite0 trunk."""
