"""One module per benchmark (``mapd bench NAME``): each prints its figures beside the baselines, as ratios."""
