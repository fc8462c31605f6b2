"""Proper names of the brightest stars, for labels on pictures (HIP number -> IAU name)."""

# IAU Working Group on Star Names (WGSN) names of the stars brighter than about magnitude 2.5.
PROPER_NAMES = {
    32349: "Sirius", 30438: "Canopus", 69673: "Arcturus", 71683: "Rigil Kentaurus", 91262: "Vega",
    24608: "Capella", 24436: "Rigel", 37279: "Procyon", 7588: "Achernar", 27989: "Betelgeuse",
    68702: "Hadar", 97649: "Altair", 60718: "Acrux", 21421: "Aldebaran", 65474: "Spica", 80763: "Antares",
    37826: "Pollux", 113368: "Fomalhaut", 102098: "Deneb", 62434: "Mimosa", 49669: "Regulus", 33579: "Adhara",
    36850: "Castor", 61084: "Gacrux", 85927: "Shaula", 25336: "Bellatrix", 25428: "Elnath", 45238: "Miaplacidus",
    26311: "Alnilam", 26727: "Alnitak", 109268: "Alnair", 62956: "Alioth", 15863: "Mirfak", 54061: "Dubhe",
    34444: "Wezen", 90185: "Kaus Australis", 41037: "Avior", 67301: "Alkaid", 86228: "Sargas", 31681: "Alhena",
    100751: "Peacock", 30324: "Mirzam", 11767: "Polaris", 46390: "Alphard", 9884: "Hamal", 3419: "Diphda",
    677: "Alpheratz", 5447: "Mirach", 14576: "Algol", 746: "Caph", 4427: "Navi", 8903: "Sheratan",
    65378: "Mizar", 53910: "Merak", 58001: "Phecda", 59774: "Megrez", 72105: "Izar", 76267: "Alphecca",
    77070: "Unukalhai", 84345: "Rasalgethi", 86032: "Rasalhague", 87833: "Eltanin", 92855: "Nunki",
    105199: "Alderamin", 107315: "Enif", 112122: "Scheat", 113881: "Markab", 113963: "Algenib",
    3179: "Schedar", 2081: "Ankaa", 27366: "Saiph", 26241: "Hatysa", 25930: "Mintaka", 28360: "Menkalinan",
    23015: "Hassaleh", 17702: "Alcyone", 35904: "Aludra", 39953: "Regor", 42913: "Alsephina",
    44816: "Suhail", 50583: "Algieba", 57632: "Denebola", 68933: "Menkent", 82273: "Atria",
    100453: "Sadr", 102488: "Aljanah", 95947: "Albireo", 98036: "Tarazed", 97278: "Alshain",
    21393: "Cursa", 25985: "Arneb", 23875: "Cursa?", 93506: "Ascella", 89931: "Kaus Media",
    88635: "Alnasl", 90496: "Kaus Borealis", 78401: "Dschubba", 80112: "Acrab",
}
PROPER_NAMES.pop(23875, None)


def star_label(hip: int) -> str:
    """``"HIP 24436 Rigel"`` for named stars, ``"HIP 12345"`` otherwise."""
    name = PROPER_NAMES.get(int(hip))
    return f"HIP {int(hip)} {name}" if name else f"HIP {int(hip)}"
