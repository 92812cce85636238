"""One module per `agv-fe` subcommand, each with ``register(subparsers)``; heavy imports stay inside ``run``."""
