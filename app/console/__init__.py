"""The browser console (viser): the operator's page for the whole procedure.

- ``server``: starts it (``launch``, ``serve``) behind ``gate``, which lets only its own page in;
- ``controller``: what the buttons do, as jobs (``jobs``) over ``core``;
- ``view``: what every tab shows, the side panel (``panel``) and the 3D scene (``scene``), with the
  pictures ``draw`` makes.
"""
