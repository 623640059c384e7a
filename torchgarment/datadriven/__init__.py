"""datadriven subpackage."""
