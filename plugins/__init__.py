"""Registry of extension points and the built-in plugins, all registered through entry points.

Kinds: rod models, insertion models, templates, TG-43 sources, exporters (:mod:`reachplan.plugins.registry`).
"""
