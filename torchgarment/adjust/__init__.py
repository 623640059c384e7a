"""adjust subpackage."""
