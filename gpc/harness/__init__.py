"""The harness: closed-loop evaluation, controller recipes, collection, stores, paired statistics; no CLI."""
