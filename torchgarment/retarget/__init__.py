"""retarget subpackage."""
