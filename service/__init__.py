"""The ins-health service: async daemon, pipeline wiring, outbox, passport store, CLI."""
