"""Procrustean Regression Networks (Park, Kwak & Lee, ECCV 2020): the PR loss, the FCN and CNN networks, training."""
