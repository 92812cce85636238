"""The `agv-fe` command line: one entry point for synthesis, simulation, replay, the service and the fleet."""
