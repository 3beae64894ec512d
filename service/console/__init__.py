"""The operator console: one page that shows what the API knows, read with the operator's own API key."""
