"""scara-record and scara-replay: runs to MCAP files and back onto the bus."""
