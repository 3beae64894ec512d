"""The v1 HTTP routes, one module per resource; handlers stay thin (validate, call the repository, commit, nudge)."""
