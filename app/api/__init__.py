"""The HTTP layer: FastAPI app factory, routes, error mapping, metrics. No recognition logic here."""
