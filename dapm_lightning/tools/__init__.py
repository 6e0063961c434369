"""Stand-alone tools built on the training core: prediction, export, data-set doctor, quickstart, CARLA."""
