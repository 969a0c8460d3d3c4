"""Procrustean Regression Networks (Park, Kwak, Lee; ECCV 2020). Work in progress: see issue 4."""
