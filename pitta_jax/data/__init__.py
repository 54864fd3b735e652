"""Dataset readers (numpy frames) and the synthetic driving benchmark."""
