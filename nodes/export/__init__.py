"""Export: results written where a production chain picks them up."""
