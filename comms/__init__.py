"""Communication: the Zenoh transport adapter and the fault wrapper used in simulation."""
