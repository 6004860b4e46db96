"""closure_confirmation: Karto's chain rule kept per submap, on the nodes' local poses it is handed."""
import numpy as np

from carto_cli.mapping.closure_confirmation import CONFIRM_NEIGHBOURS, ClosureConfirmation
from carto_cli.mapping.constraint_builder import LoopClosure

# Ten nodes of trajectory 0 along x, 0.5 m apart, then two of trajectory 1.
LOCAL = np.array([[0.5 * i, 0.0, 0.0] for i in range(10)] + [[0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])
TRAJECTORIES = [0] * 10 + [1, 1]


def _closure(node, x, y=0.0, submap=0):
    return LoopClosure(node, submap, np.array([x, y, 0.0]), 0.6, False)


def test_a_closure_waits_until_a_neighbours_closure_agrees_with_local_slam():
    c = ClosureConfirmation()
    first = _closure(9, 4.5)
    assert c.agreeing(first, LOCAL, TRAJECTORIES) == [] and c.keep(first, []) == []
    assert c.unconfirmed == 1
    off = _closure(7, 3.5, 1.0)  # 1 m off what local SLAM says between nodes 7 and 9
    assert c.agreeing(off, LOCAL, TRAJECTORIES) == []
    c.keep(off, [])
    agreeing_one = _closure(8, 4.0)
    agreeing = c.agreeing(agreeing_one, LOCAL, TRAJECTORIES)
    assert [e.node for e in agreeing] == [9]
    newly = c.keep(agreeing_one, agreeing)
    assert [e.node for e in newly] == [9] and newly[0].inserted
    assert c.unconfirmed == 1  # node 7's still waits
    # Already inserted: a later agreeing closure does not insert node 9's again.
    again = _closure(8, 4.0)
    assert [e.node for e in c.keep(again, c.agreeing(again, LOCAL, TRAJECTORIES))] == []


def test_closures_of_other_trajectories_or_submaps_never_agree():
    c = ClosureConfirmation()
    c.keep(_closure(1, 0.5), [])
    assert c.agreeing(_closure(11, 0.5), LOCAL, TRAJECTORIES) == []  # trajectory 1
    assert c.agreeing(_closure(2, 1.0, submap=1), LOCAL, TRAJECTORIES) == []  # another submap
    assert [e.node for e in c.agreeing(_closure(2, 1.0), LOCAL, TRAJECTORIES)] == [1]


def test_neighbours_are_the_nearest_searchable_nodes_of_the_trajectory():
    c = ClosureConfirmation()
    points = [np.zeros((5, 2))] * 12
    points[6] = np.zeros((0, 2))  # an empty scan cannot be matched
    c.keep(_closure(4, 2.0), [])  # already has a closure to submap 0
    assert CONFIRM_NEIGHBOURS == 2 and c.neighbours(5, 0, [3], TRAJECTORIES, points) == [7, 2]
    assert c.neighbours(9, 0, [], TRAJECTORIES, points) == [8, 7]  # never trajectory 1's nodes 10 and 11


def test_two_trajectories_are_linked_when_closures_from_two_places_agree():
    from carto_cli.core import transform
    from carto_cli.mapping.closure_confirmation import LinkConfirmation

    # Trajectory 1's frame lies at (5, 2, 90 deg) in trajectory 0's; a closure's node pose in its submap's frame
    # follows from that, for a node at ``local`` (trajectory 1) and a submap at ``origin`` (trajectory 0).
    frame = np.array([5.0, 2.0, np.pi / 2])

    def closure(node, submap, local, origin, off=(0.0, 0.0, 0.0)):
        in_map = transform.compose(transform.compose(frame, off), local)
        return LoopClosure(node, submap, transform.compose(transform.inverse(origin), in_map), 0.7, True)

    origin0, origin1 = np.array([0.0, 0.0, 0.0]), np.array([4.0, 0.0, 0.0])
    links = LinkConfirmation()
    local = np.array([1.0, 0.5, 0.1])
    assert links.offer(closure(3, 0, local, origin0), 0, origin0, 1, local) == ([], None)  # alone: waits
    # A neighbouring node's closure is no independent evidence, into the same submap or another (every scan lies
    # in two); a look-alike elsewhere disagrees
    assert links.offer(closure(4, 0, local + 0.1, origin0), 0, origin0, 1, local + 0.1)[0] == []
    assert links.offer(closure(7, 1, local + 0.2, origin1), 0, origin1, 1, local + 0.2)[0] == []
    far = local + np.array([2.5, 0.0, 0.0])
    wrong = closure(5, 1, far, origin1, off=(0.0, 0.0, np.pi))
    assert links.offer(wrong, 0, origin1, 1, far)[0] == []
    # Both placements wait; each is followed by its newest closure, the newest placement first
    assert [c.node for c in links.waiting(1)] == [5, 7] and links.waiting(2) == []
    found, got = links.offer(closure(6, 1, far, origin1), 0, origin1, 1, far)
    assert [c.node for c in found] == [3, 4, 7, 6] and got is not None
    np.testing.assert_allclose(got, frame, atol=1e-9)
    assert links.pending == {}
    # Offered the other way round (the later trajectory's submap, the earlier one's node): the same frame
    back = LinkConfirmation()
    node0 = np.array([6.0, 3.0, 0.4])  # trajectory 0's node, matched in trajectory 1's submap at origin1
    rel = transform.compose(transform.inverse(transform.compose(frame, origin1)), node0)
    back.offer(LoopClosure(1, 7, rel, 0.7, True), 1, origin1, 0, node0)
    second = transform.compose(transform.inverse(transform.compose(frame, origin0)), node0)
    found, got = back.offer(LoopClosure(2, 8, second, 0.7, True), 1, origin0, 0, node0)
    assert len(found) == 2
    np.testing.assert_allclose(got, frame, atol=1e-9)
