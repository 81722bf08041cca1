"""What the tests share that the product does not use: test data location, skips."""
