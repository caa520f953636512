"""The files gtforge writes and its stages and reports read (pydantic models with a schema_version); no stage logic."""
