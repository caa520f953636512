"""Reports people read: self-contained HTML pages and tables, one module per stage."""
