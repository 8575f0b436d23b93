"""Training: the network from scratch on procedural scenes (from_scratch), and SC-NeRF's heads on a
frozen backbone initialised from MVSNeRF's weights (finetune)."""
