"""The shared runtime of the services: Zenoh sessions, messages, topics, clocks, loops."""
