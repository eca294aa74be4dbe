"""The data contract: Parquet schemas, validation, reading sessions, results tables."""
