"""Accuracy evaluation of pipeline outputs against analytic ground truth."""
