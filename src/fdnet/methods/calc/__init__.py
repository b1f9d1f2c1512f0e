"""CALC (Merrill and Huang, RSS 2018): an auto-encoder reconstructing HOG, trained without labels."""
