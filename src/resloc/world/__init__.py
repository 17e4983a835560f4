"""The simulated world: robots, leader-follower control, danger zones, attacks, network."""
