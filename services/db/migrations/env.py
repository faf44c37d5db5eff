"""Alembic environment: migrate the connection handed over by ``services.db.engine.migrate``,
or the database of the current settings when run as ``alembic upgrade head``."""

from alembic import context

from services.db.engine import make_engine
from services.db.models import Base
from services.settings import get_settings

target_metadata = Base.metadata


def run_migrations_online() -> None:
    connection = context.config.attributes.get("connection")
    if connection is not None:
        context.configure(connection=connection, target_metadata=target_metadata, render_as_batch=True)
        with context.begin_transaction():
            context.run_migrations()
        return
    settings = get_settings()
    engine = make_engine(settings.resolved_database_url, settings.database_schema)
    with engine.connect() as connection:
        context.configure(connection=connection, target_metadata=target_metadata, render_as_batch=True)
        with context.begin_transaction():
            context.run_migrations()
        connection.commit()


run_migrations_online()
