"""Pipeline stages. Every module here is imported by the registry; each defines Node subclasses."""
