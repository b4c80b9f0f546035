"""The live system: wire messages, the Zenoh bus, the service, the client, record and replay,
Rerun and systemd. Moves data; the math it calls lives in `core`."""
