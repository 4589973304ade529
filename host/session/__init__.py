"""The session: the `Host` façade (`core`) and its parts — the chips heard (`registry`), command
rounds (`commands`), bring-up, the SYNC driver, the watchdog, recovery, gateways, events and errors."""
