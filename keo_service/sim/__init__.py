"""Simulation that knows the truth: the simulator, joint trajectories, the reference paper's
experiments and the delay study."""
