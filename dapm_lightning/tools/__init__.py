"""Programs built on the core: one-line prediction, export, data-set doctor, synth, quickstart, CARLA, evaluation."""
