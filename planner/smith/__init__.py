"""Smith et al. 2018's baseline (``smith.plan``), its viewing directions and its heuristic."""
