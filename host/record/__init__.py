"""Recording and replay: the MCAP recorder and reader (`recording`), its protobuf channels
(`schema`), and replay as a transport."""
