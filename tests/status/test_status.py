"""The one status vocabulary: names, codes, and arrays that never cut a name."""
import numpy as np
import pytest

from lightning_bodyschema.deploy.module import STATUS_CODES as PACKAGE_CODES
from lightning_bodyschema.status import STATUS_CODES, Status, status_array, status_codes, status_names


def test_members_are_their_names_and_codes_round_trip():
    assert Status.OK == "ok" and str(Status.INFEASIBLE_LEARNED) == "infeasible_learned"
    for member in Status:
        assert Status.from_code(member.code) is member and STATUS_CODES[member.value] == member.code
    assert len({m.code for m in Status}) == len(Status)
    with pytest.raises(ValueError, match="unknown status code 99"):
        Status.from_code(99)


# The contract, written out once more by hand: every file, exported package and the C++ examples read these integers.
# Reordering, renaming or renumbering a member must fail here (the module's own mapping is not compared with itself).
PINNED = {"ok": 0, "non_finite": 1, "out_of_range": 2, "fault_not_met": 3, "bad_input": 4, "infeasible": 5,
          "infeasible_learned": 6, "unreachable": 7, "unchecked": 8, "not_converged": 9, "activation_above_one": 10,
          "no_fault": 11, "identified": 12, "ambiguous": 13, "not_identifiable": 14}


def test_every_name_keeps_its_code():
    assert {m.value: m.code for m in Status} == PINNED
    assert STATUS_CODES == PINNED
    assert [Status.from_code(code).value for code in sorted(PINNED.values())] == sorted(PINNED, key=PINNED.get)
    assert list(status_array(np.arange(len(PINNED)))) == [Status(name) for name in sorted(PINNED, key=PINNED.get)]


def test_package_codes_are_the_vocabulary():
    """The codes the exported package and the C++ examples already use keep their meaning."""
    for name, code in PACKAGE_CODES.items():
        assert Status(name).code == code


def test_arrays_keep_long_names_and_compare_with_strings():
    arr = status_array(["ok", Status.INFEASIBLE_LEARNED, 1, "activation_above_one"])
    assert list(arr == "ok") == [True, False, False, False]
    assert arr[1] == "infeasible_learned" and arr[2] is Status.NON_FINITE
    names = status_names(arr)
    assert names[3] == "activation_above_one" and names[1] == "infeasible_learned"  # not cut to 16 characters
    assert list(status_codes(names)) == [m.code for m in arr]
    assert list(status_array("ok", size=3) == "ok") == [True] * 3
    with pytest.raises(ValueError):
        status_array(["no_such_status"])


def test_codes_to_members_vectorized_is_the_vocabulary():
    from lightning_bodyschema.adaptation.command import statuses

    codes = np.array([m.code for m in Status][::-1], np.int32)
    assert list(statuses(codes)) == list(Status)[::-1] and statuses(codes).dtype == object


def test_an_unknown_code_in_an_array_is_refused():
    with pytest.raises(ValueError, match="unknown status code 99"):
        status_array(np.array([0, 99]))
    with pytest.raises(ValueError, match="unknown status code -1"):
        status_array(np.array([-1], np.int32))
