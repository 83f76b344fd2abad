"""gchgg: graph-curriculum-guided hindsight goal generation (GC-HGG) and its baselines as TorchRL parts."""
