"""SC-NeRF (and its MVSNeRF baseline) in PyTorch, one module per stage of the paper, its symbols as
names: G1 (encoder), the cost volume P and G2 (cost_volume), per-point features (points), M1
(trunk), the rectifiers (rectifiers), M4 (colour), M2 and compositing (renderer), the whole
network (network), and its weights on disk (checkpoint)."""
