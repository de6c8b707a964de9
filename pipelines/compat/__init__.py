"""Workarounds for library versions, one module per library. Each names the version it is for and
when to delete it, so that an upgrade removes it in one commit."""
