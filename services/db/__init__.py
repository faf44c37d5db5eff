"""The service database: SQLAlchemy 2 models, engine/session set-up and Alembic migration to head."""
