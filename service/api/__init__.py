"""The HTTP face of the service: app factory, routes by resource, schemas and error handling."""

from service.api.app import create_app

__all__ = ["create_app"]
