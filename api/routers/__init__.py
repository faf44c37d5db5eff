"""One router per resource: thin functions that validate, call services/ and shape the answer."""
