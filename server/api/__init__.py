"""REST API under ``/api/v1``: one router per resource, request/response schemas in ``schemas``."""
