"""What every role and transport shares: the bus and the clock a node sees, the messages
and their periods, the topics, the roles, the visual topics, node configs, the 1 kHz
cycle engine, loop timing and worker pools."""
