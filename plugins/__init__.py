"""Registry of extension points (rod models, insertion models, templates, TG-43 sources, exporters)
and the built-in plugins, all registered through entry points."""
