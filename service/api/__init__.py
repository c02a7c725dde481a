"""The REST API: one router per resource, each with its path prefix."""
