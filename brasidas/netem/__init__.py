"""A test network and link emulator: namespaces as hosts, a userspace bridge port that impairs.

:mod:`~brasidas.netem.core` is the impairment schedule (sans-IO), :mod:`~brasidas.netem.relay`
the bridge port that applies it, :mod:`~brasidas.netem.netns` the network of namespaces the tests
and ``make net-demo`` build.
"""
