"""The run room: the chain from a case's structures to its delivered plan and files (``run_case``)."""
