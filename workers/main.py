"""Entry module for ``dramatiq workers.main``: the broker of the environment's settings, actors declared."""

from services.settings import get_settings
from workers.broker import setup_broker

broker = setup_broker(get_settings())
