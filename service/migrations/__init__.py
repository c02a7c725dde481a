"""The database's schema history, as Alembic migrations (see :func:`service.store.migrate`)."""
