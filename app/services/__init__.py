"""The composition roots: each builds a page and what it shows from the parts below it.

``live`` (the operator's service: the loop, its page, its recorder), ``replay`` (a
recording played back on a page of its own), ``fleet_page`` (a fleet's one page), and
``recording`` (a live service's recorder started as the CLI asks). Nothing below imports
from here."""
