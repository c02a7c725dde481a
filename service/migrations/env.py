"""Alembic's entry point: migrations run on the connection :func:`service.store.migrate` hands
over (``config.attributes["connection"]``), inside its transaction and lock."""

from __future__ import annotations

from alembic import context

from service.store import Base

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError(
        "teachpath's migrations run from the service (service.store.migrate), which passes its "
        "connection; to upgrade a database by hand, start `teachpath serve` or open a Store on it"
    )
context.configure(
    connection=connection,
    target_metadata=Base.metadata,
    # SQLite alters a column by copying its table: the migrations say where (batch_alter_table).
    render_as_batch=connection.dialect.name == "sqlite",
    compare_type=True,
)
with context.begin_transaction():
    context.run_migrations()
