"""Map matching of fused vehicle positions: online per-vehicle filtering and batch Viterbi."""
