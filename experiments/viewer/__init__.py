"""The session viewer: ``skinstretch view`` serves one session and its results (or the trial being recorded, with
a live analysis) to a local browser page. See :mod:`skinstretch.experiments.viewer.server`."""
