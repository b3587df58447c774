"""The three branches and what they share.

Importing the package registers every branch (`cogs.branches.base.REGISTRY`), in the
order of their one-hot channels: a new branch is its own module plus one line here.
"""

from cogs.branches import human, object, scene  # noqa: F401  (registration, in channel order)
