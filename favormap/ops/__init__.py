"""ops: map operations (visibility, merge, prune, export)."""
