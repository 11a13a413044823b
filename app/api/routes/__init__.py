"""The service's endpoints, one module per part: locate, references (and their jobs), ops. Each handler
parses the request, calls the service, shapes JSON. ``ROUTERS`` in the order the app includes them (the
order of /openapi.json); ``ROUTES``, their routes, is where the body-limit middleware (app/api/limits.py)
finds the route a request is for: an included router is not a list of routes it can match one by one."""

from app.api.routes import library, locate, ops, references, sequence

ROUTERS = (locate.router, sequence.router, references.router, ops.router, library.router)
ROUTES = tuple(route for router in ROUTERS for route in router.routes)
