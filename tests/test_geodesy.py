"""geodesy: the ENU frame at an origin."""


def test_enu_origin_from_numpy_scalars_gives_the_same_frame() -> None:
    """A numpy float64 origin once printed as 'np.float64(...)' into the PROJ string (ENU off by ~500 km)."""
    import numpy as np

    from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu

    plain = EnuOrigin(-35.363261, 149.16523, 584.0)
    wrapped = EnuOrigin(np.float64(-35.363261), np.float64(149.16523), np.float64(584.0))
    a = geodetic_to_enu(-35.3632, 149.1653, 585.0, wrapped)
    b = geodetic_to_enu(-35.3632, 149.1653, 585.0, plain)
    assert np.allclose(a, b, atol=1e-9) and float(np.linalg.norm(a)) < 20.0
